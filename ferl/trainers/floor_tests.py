"""Test phases of §3.5: held-out test images shown to the actor before and after training.

* greedy actions argmin_a F(z, a) for n test images per class at every test-noise level
  (Fig. 3.6, noise tolerance)
* softmax action probabilities, Eq. (3.11), at the training noise level (Fig. 3.7, outliers)
* hidden activations at the training noise level: the bracket of Eq. (3.12), averaged over
  actions, and the marginal Σ_a P(h|z, a) P(a|z) of footnote 6 (Fig. 3.10)

The environment is a digit floor: it names its tile ``classes``, their ``class_optimal_action``,
its ``arrangement``, ``action_names`` and training ``noise``.
"""

from typing import Annotated, Literal

import numpy as np
import torch

from ferl.config.params import Allowed, ConfigError, PositiveInt
from ferl.data import DataError, MnistSplit, add_pixel_noise
from ferl.envs.digit_floor import NOISE_CLASS
from ferl.images import as_images, tile, weight_images
from ferl.interfaces import ActorViews
from ferl.run.tensorboard import log_embedding, log_weights
from ferl.stats import greedy_accuracy
from ferl.trainers.phased import Phase

EMBEDDED_PER_CLASS = 100  # test digits per class in the projector (TensorBoard tags: docs/records.md)


def noise_levels(levels) -> bool:
    """Test-noise levels: at least one, each a fraction of pixels in [0, 1]."""
    return len(levels) > 0 and all(0 <= x <= 1 for x in levels)


def floor_test_images(classes, data: MnistSplit, n_per_class: int, generator) -> torch.Tensor:
    """(C, n, 784) clean test images per floor class: the first n held-out test images of
    each digit (never used for tiles), independent pure-noise images for class "N"."""
    images = []
    for label in classes:
        if label == NOISE_CLASS:
            images.append(
                torch.rand(n_per_class, data.test_images.shape[1], generator=generator, device=generator.device)
            )
        else:
            images.append(data.test_by_class(int(label), n_per_class).to(generator.device))
    return torch.stack(images)


@torch.no_grad()
def evaluate_floor(actor, clean: torch.Tensor, noise_levels, probe_noise: float, beta: float, generator) -> dict:
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
    hidden = actor.hidden(x)  # (R, C·n, nA, H)
    shape = (F.shape[0], n_classes, n)
    return {
        "greedy_counts": torch.stack(counts, 1).cpu().numpy().astype(np.int64),
        "probs": probs.view(*shape, -1).cpu().numpy().astype(np.float32),
        "hidden": hidden.mean(2).view(*shape, -1).cpu().numpy().astype(np.float32),
        "hidden_marginal": (probs.unsqueeze(-1) * hidden).sum(2).view(*shape, -1).cpu().numpy().astype(np.float32),
        "probe_images": probe.cpu().numpy().astype(np.float16),
    }


def json_values(x: np.ndarray) -> list:
    """Per-run values for summary.json; NaN (no optimal action to score, e.g. without reward) → null."""
    return [None if np.isnan(v) else float(v) for v in x]


class GreedyTests(Phase):
    """The test phase ``when`` = "before" or "after" training: the actor's responses to the same
    ``test_per_class`` held-out images per class at every level of ``test_noise_levels`` (drawn
    once, when the trainer is set up), at β of the end of training; ``last_step``: the training
    phase's steps, where the "after" test logs. After training it writes
    ``floor_test.npz`` and the metrics ``greedy_accuracy`` and ``greedy_accuracy_before`` (per
    test-noise level), and shows run 0's weights and test-digit activations in TensorBoard."""

    def __init__(
        self,
        when: Literal["before", "after"],
        test_per_class: PositiveInt,
        test_noise_levels: Annotated[list[float], Allowed(noise_levels, "(noise levels in [0, 1], at least one)")],
        last_step: PositiveInt,
    ):
        self.when, self.test_per_class, self.levels = when, test_per_class, list(test_noise_levels)
        self.last_step = last_step if when == "after" else 0

    def applies(self, job) -> bool:
        """The tests show held-out images: not to an actor that sees the floor's true state."""
        return job.env.describe()["observation"] == "image"

    def prepare(self, job) -> None:
        if not isinstance(job.actor, ActorViews):  # the records are its hidden activations (Fig. 3.10)
            raise ConfigError(
                f"actor: {type(job.actor).__qualname__} lacks hidden, state_weights (the floor's "
                "tests record them: ferl/interfaces.py, ActorViews)"
            )
        if job.prepared.floor_test_images is not None:  # the other test phase drew them
            return
        try:
            job.prepared.floor_test_images = floor_test_images(
                job.env.classes, job.data, self.test_per_class, job.generator
            )
        except DataError as e:
            raise ConfigError(f"trainer.test_per_class={self.test_per_class} is not allowed: {e}") from None

    def metric_names(self, job) -> list[str]:
        if self.when == "before":
            return []
        return [f"{name}/{level:g}" for name in ("greedy_accuracy", "greedy_accuracy_before") for level in self.levels]

    def run_bytes(self, job) -> int:
        """The peak of ``run`` (``ferl.run.footprint``'s hook): per run and test image, float32
        activations (A, H) three times over (x, hidden, probs × hidden) and their records (H twice,
        A probabilities); the noisy images once."""
        classes, n, pixels = job.prepared.floor_test_images.shape
        A, H = job.env.n_actions, job.actor.state_weights().shape[-1]  # W (R, S, H)
        return 4 * classes * n * (job.R * (3 * A * H + 3 * A + 2 * H) + pixels)

    def run(self, job, state) -> None:
        result = evaluate_floor(
            job.actor,
            job.prepared.floor_test_images,
            self.levels,
            job.env.noise,
            job.actor.inverse_temperature(1.0),
            job.generator,
        )
        step = 0 if self.when == "before" else self.last_step
        self.log_actor(job, step)
        self.log_accuracy(job, result, step)
        if self.when == "before":
            # what the records take of it: not its noisy images (the records keep the last test's),
            # which would be a third of every checkpoint until then (5.6 MB at 9 × 400 images)
            job.outputs.floor_test_before = {k: v for k, v in result.items() if k != "probe_images"}
            return
        self.log_test_digits(job, result, step)
        before, env = job.outputs.floor_test_before, job.env
        job.outputs.floor_test_before = None
        job.run.save_records(
            "floor_test",
            job.R,
            noise_levels=np.asarray(self.levels, dtype=np.float64),
            classes=np.array(env.classes),
            optimal_action=env.class_optimal_action.astype(np.int64),
            action_names=np.array(env.action_names),
            arrangement=env.arrangement,
            probe_noise=np.float64(env.noise),
            beta=np.float64(job.actor.inverse_temperature(1.0)),
            clean_images=job.prepared.floor_test_images.cpu().numpy().astype(np.float16),
            probe_images=result["probe_images"],
            **{
                f"{key}_{phase}": res[key]
                for phase, res in (("before", before), ("after", result))
                for key in ("greedy_counts", "probs", "hidden", "hidden_marginal")
            },
        )
        levels = [f"{x:g}" for x in self.levels]
        for name, res in (("greedy_accuracy", result), ("greedy_accuracy_before", before)):
            accuracy = greedy_accuracy(res["greedy_counts"], env.class_optimal_action)
            job.metrics[name] = {lvl: json_values(accuracy[:, i]) for i, lvl in enumerate(levels)}

    def log_actor(self, job, step: int) -> None:
        """Run 0's weights: histograms and the 28 × 28 image→hidden tiles (Fig. 3.5)."""
        log_weights(job.writer, "actor", job.actor, step)
        job.writer.add_image("actor/W_sh_images", tile(weight_images(job.actor.state_weights())[:, 0]), step)

    def log_accuracy(self, job, result: dict, step: int) -> None:
        """Greedy accuracy per test-noise level, mean over runs (Fig. 3.6)."""
        accuracy = greedy_accuracy(result["greedy_counts"], job.env.class_optimal_action)
        for i, level in enumerate(self.levels):
            if not np.isnan(accuracy[:, i]).all():
                job.writer.add_scalar(f"test/greedy_accuracy_{level:g}", float(np.nanmean(accuracy[:, i])), step)

    def log_test_digits(self, job, after: dict, step: int) -> None:
        """Sample observations (clean test images and the noisy ones the actor was probed with,
        one row per class) and run 0's hidden activations per test digit in the projector."""
        env, images, writer = job.env, job.prepared.floor_test_images, job.writer
        n = min(8, images.shape[1])
        writer.add_image("test/observations_clean", tile(as_images(images[:, :n])), step)
        writer.add_image("test/observations_noisy", tile(as_images(after["probe_images"][:, :n])), step)
        C, k = images.shape[0], min(EMBEDDED_PER_CLASS, images.shape[1])
        names = env.action_names
        greedy = after["probs"][0, :, :k].argmax(-1)  # (C, k): softmax is monotone in −F at β > 0
        log_embedding(
            writer,
            "actor/hidden_test_digits",
            after["hidden"][0, :, :k].reshape(C * k, -1),
            {
                "class": np.repeat(np.asarray(env.classes), k),
                "optimal_action": np.repeat([names[a] if a >= 0 else "none" for a in env.class_optimal_action], k),
                "greedy_action": [names[a] for a in greedy.reshape(-1)],
            },
            step,
            images=after["probe_images"][:, :k],
        )
