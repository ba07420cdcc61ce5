"""Synthetic digit-floor run directories following docs/records.md, for analysis tests.

The records are built so that the answers are known: after training the greedy
action is the optimal one for most test images, hidden activations cluster by
optimal action (so every same-action pair forms its own cluster), and the image
templates of "7" and "8" are near copies of "1" and "3" (low mutual information).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

CLASSES = [str(d) for d in range(9)]
ARRANGEMENT = np.array(CLASSES).reshape(3, 3)
ACTIONS = ["N", "E", "S", "W"]
CW_OPTIMAL = {"0": "E", "1": "S", "2": "S", "3": "E", "4": None, "5": "W", "6": "N",
              "7": "N", "8": "W", "N": "W"}
NEAR_COPIES = {"7": "1", "8": "3"}
PIXELS = 784


def _optimal_actions(classes: list[str]) -> np.ndarray:
    return np.array([-1 if CW_OPTIMAL[c] is None else ACTIONS.index(CW_OPTIMAL[c])
                     for c in classes], dtype=np.int64)


def _greedy_counts(rng, n_runs, noise_levels, optimal, n_images, trained: bool) -> np.ndarray:
    n_actions = len(ACTIONS)
    counts = np.empty((n_runs, len(noise_levels), len(optimal), n_actions), dtype=np.int64)
    for l, noise in enumerate(noise_levels):
        # Trained agents stay accurate up to 37.5 % test noise, then decline (Fig. 3.6(c)).
        p_opt = max(0.25, 0.95 - 1.5 * max(0.0, noise - 0.375)) if trained else 0.25
        for c, a in enumerate(optimal):
            p = np.full(n_actions, 1 / n_actions)
            if a >= 0:
                p = np.full(n_actions, (1 - p_opt) / (n_actions - 1))
                p[a] = p_opt
            counts[:, l, c] = rng.multinomial(n_images, p, size=n_runs)
    return counts


def _action_probs(rng, n_runs, optimal, n_images, trained: bool) -> np.ndarray:
    alpha = np.ones((len(optimal), len(ACTIONS)))
    if trained:
        alpha[optimal >= 0, optimal[optimal >= 0]] = 12.0
    return np.stack([[rng.dirichlet(alpha[c], size=n_images) for c in range(len(optimal))]
                     for _ in range(n_runs)]).astype(np.float32)


def _hidden(rng, n_runs, optimal, n_images, n_hidden, trained: bool) -> np.ndarray:
    shape = (n_runs, len(optimal), n_images, n_hidden)
    if not trained:
        return rng.uniform(0.4, 0.6, size=shape).astype(np.float32)
    # One activation prototype per optimal action (goal: its own) and run.
    protos = rng.uniform(0, 1, size=(n_runs, len(ACTIONS) + 1, n_hidden))
    mean = protos[:, optimal, None, :]  # optimal = −1 picks the goal's prototype
    return np.clip(mean + rng.normal(0, 0.03, size=shape), 0, 1).astype(np.float32)


def _clean_images(rng, classes, n_images) -> np.ndarray:
    templates = {c: rng.random(PIXELS) < 0.2 for c in classes if c not in NEAR_COPIES}
    for copy, original in NEAR_COPIES.items():
        if copy in classes:
            templates[copy] = templates[original] ^ (rng.random(PIXELS) < 0.03)
    clean = np.empty((len(classes), n_images, PIXELS))
    for k, c in enumerate(classes):
        if c == "N":
            clean[k] = rng.random((n_images, PIXELS))
        else:
            flip = rng.random((n_images, PIXELS)) < 0.05
            clean[k] = (templates[c][None, :] ^ flip) * rng.uniform(0.7, 1.0, (n_images, PIXELS))
    return clean


def _with_noise(rng, images: np.ndarray, noise: float) -> np.ndarray:
    replaced = rng.random(images.shape) < noise
    return np.where(replaced, rng.random(images.shape), images)


def make_floor_run(run_dir: Path, *, n_runs: int = 2, steps: int = 500, n_images: int = 20,
                   n_hidden: int = 5, classes: list[str] | None = None, reward: bool = True,
                   probe_noise: float = 0.125, seed: int = 0,
                   experiment: str = "ch3_floor_synthetic") -> Path:
    """Write a complete synthetic digit-floor run into `run_dir` and return it."""
    rng = np.random.default_rng(seed)
    classes = list(CLASSES if classes is None else classes)
    optimal = _optimal_actions(classes)
    noise_levels = np.arange(9) / 8
    records = run_dir / "records"
    records.mkdir(parents=True)

    # Reward/step rises from ≈0 to ≈7.5 over training; exactly 0 without reward.
    p_good = np.linspace(0.1, 0.95, steps)
    good = rng.random((n_runs, steps)) < p_good
    rewards = np.where(good, rng.choice([10.0, 4.0], size=good.shape, p=[1 / 3, 2 / 3]), -2.0)
    rewards = (rewards if reward else np.zeros_like(rewards)).astype(np.float32)
    np.savez(records / "floor_train.npz", rewards=rewards,
             td_errors=rng.normal(size=(n_runs, steps)).astype(np.float32))

    clean = _clean_images(rng, classes, n_images)
    test = dict(noise_levels=noise_levels, classes=np.array(classes), optimal_action=optimal,
                action_names=np.array(ACTIONS), arrangement=ARRANGEMENT.copy(),
                probe_noise=np.float64(probe_noise), beta=np.float64(2.0),
                probe_images=_with_noise(rng, clean, probe_noise).astype(np.float16),
                clean_images=clean.astype(np.float16))
    if "N" in classes:
        test["arrangement"] = np.where(ARRANGEMENT == "5", "N", ARRANGEMENT)
    for phase, trained in (("before", False), ("after", reward)):
        test[f"greedy_counts_{phase}"] = _greedy_counts(rng, n_runs, noise_levels, optimal,
                                                        n_images, trained)
        test[f"probs_{phase}"] = _action_probs(rng, n_runs, optimal, n_images, trained)
        hidden = _hidden(rng, n_runs, optimal, n_images, n_hidden, trained)
        test[f"hidden_{phase}"] = hidden
        test[f"hidden_marginal_{phase}"] = hidden if reward else 0.05 * hidden
    np.savez(records / "floor_test.npz", **test)
    np.savez(records / "weights.npz",
             W_sh_before=rng.normal(0, 0.01, (n_runs, PIXELS, n_hidden)).astype(np.float32),
             W_sh_after=rng.normal(0, 0.3, (n_runs, PIXELS, n_hidden)).astype(np.float32))

    scored = optimal >= 0
    after = test["greedy_counts_after"]
    accuracy = after[:, :, scored, optimal[scored]].sum(-1) / after[:, :, scored].sum((-1, -2))
    summary = {
        "experiment": experiment, "task": "digit_floor",
        "seeds": list(range(seed, seed + n_runs)),
        "metrics": {
            "reward_per_step_last10pct": rewards[:, -steps // 10:].mean(axis=1).tolist(),
            "greedy_accuracy": {f"{x:g}": accuracy[:, l].tolist()
                                for l, x in enumerate(noise_levels)},
        },
        "optimal": {"reward_per_step": 8.0},
        "wall_time_s": 1.0, "agent_steps_per_s": 1000.0,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    (run_dir / ".hydra").mkdir()
    (run_dir / ".hydra" / "config.yaml").write_text(f"experiment: {experiment}\nseed: {seed}\n")
    (run_dir / "checkpoints").mkdir()
    (run_dir / "checkpoints" / "last.pt").write_bytes(b"synthetic checkpoint")
    (run_dir / "tb").mkdir()
    return run_dir
