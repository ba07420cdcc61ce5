"""Test phase of §3.5: held-out test images shown to the actor before and after training.

* greedy actions argmin_a F(z, a) for n test images per class at every test-noise level
  (Fig. 3.6, noise tolerance)
* softmax action probabilities, Eq. (3.11), at the training noise level (Fig. 3.7, outliers)
* hidden activations at the training noise level: the bracket of Eq. (3.12), averaged over
  actions, and the marginal Σ_a P(h|z, a) P(a|z) of footnote 6 (Fig. 3.10)
"""
import numpy as np
import torch

from ferl.data import MnistSplit, add_pixel_noise
from ferl.envs.digit_floor import NOISE_CLASS


def floor_test_images(classes, data: MnistSplit, n_per_class: int, generator) -> torch.Tensor:
    """(C, n, 784) clean test images per floor class: the first n held-out test images of
    each digit (never used for tiles), independent pure-noise images for class "N"."""
    images = []
    for label in classes:
        if label == NOISE_CLASS:
            images.append(torch.rand(n_per_class, data.test_images.shape[1], generator=generator,
                                     device=generator.device))
        else:
            images.append(data.test_by_class(int(label), n_per_class).to(generator.device))
    return torch.stack(images)


@torch.no_grad()
def evaluate_floor(actor, clean: torch.Tensor, noise_levels, probe_noise: float, beta: float,
                   generator) -> dict:
    """Responses of every run to the same noisy test images; numpy arrays as in docs/records.md."""
    n_classes, n, n_pixels = clean.shape
    counts = []
    for level in noise_levels:
        noisy = add_pixel_noise(clean, level, generator).view(-1, n_pixels)
        F, _ = actor.evaluate(noisy)
        greedy = torch.nn.functional.one_hot(F.argmin(-1), F.shape[-1])  # (R, C·n, nA)
        counts.append(greedy.view(F.shape[0], n_classes, n, -1).sum(2))
    probe = add_pixel_noise(clean, probe_noise, generator)
    F, x = actor.evaluate(probe.view(-1, n_pixels))
    probs = actor.policy(F, beta)
    hidden = torch.sigmoid(x)  # (R, C·n, nA, H)
    shape = (F.shape[0], n_classes, n)
    return {
        "greedy_counts": torch.stack(counts, 1).cpu().numpy().astype(np.int64),
        "probs": probs.view(*shape, -1).cpu().numpy().astype(np.float32),
        "hidden": hidden.mean(2).view(*shape, -1).cpu().numpy().astype(np.float32),
        "hidden_marginal": (probs.unsqueeze(-1) * hidden).sum(2).view(*shape, -1).cpu().numpy().astype(np.float32),
        "probe_images": probe.cpu().numpy().astype(np.float16),
    }


def greedy_accuracy(greedy_counts: np.ndarray, optimal_action) -> np.ndarray:
    """Fraction of test images whose greedy action is optimal (Fig. 3.6).

    ``greedy_counts`` is (R, L, C, nA): per run, test-noise level and class, how many of the n
    test images made each action greedy. Classes without a unique optimal action (the goal;
    every class without reward) are excluded. Returns (R, L); NaN when no class is scored.
    """
    counts = np.asarray(greedy_counts, dtype=np.float64)
    actions = np.asarray(optimal_action)
    scored = np.flatnonzero(actions >= 0)
    if scored.size == 0:
        return np.full(counts.shape[:2], np.nan)
    correct = counts[:, :, scored, actions[scored]].sum(axis=-1)
    return correct / counts[:, :, scored, :].sum(axis=(-1, -2))
