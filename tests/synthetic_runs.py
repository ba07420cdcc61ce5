"""Synthetic run directories following docs/records.md, for analysis tests.

Each writes `records/run.json` as a real run does (what produced it: task, trainer,
environment, preprocessor, predictors, actor) and the records its trainer would. The records
are built so that the answers are known. Digit floor (`make_floor_run`): after training the
greedy action is the optimal one for most test images, hidden activations cluster by optimal
action (so every same-action pair forms its own cluster), and the image templates of "7" and
"8" are near copies of "1" and "3" (low mutual information). T-maze (`make_tmaze_run`,
chapter 4; `make_ch5_run`, chapter 5) and a run of an unknown task (`make_toy_run`): see their
docstrings.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ferl.analysis.records import Manifest, Run

CLASSES = [str(d) for d in range(9)]
ARRANGEMENT = np.array(CLASSES).reshape(3, 3)
ACTIONS = ["N", "E", "S", "W"]
CW_OPTIMAL = {"0": "E", "1": "S", "2": "S", "3": "E", "4": None, "5": "W", "6": "N", "7": "N", "8": "W", "N": "W"}
NEAR_COPIES = {"7": "1", "8": "3"}
PIXELS = 784


def write_manifest(
    run_dir: Path,
    task: str,
    experiment: str,
    trainer: dict,
    env: dict,
    predictors: dict | None = None,
    preprocessor: dict | None = None,
    actor: dict | None = None,
) -> None:
    """records/run.json (docs/records.md)."""
    manifest = {
        "task": task,
        "experiment": experiment,
        "trainer": {"class": "synthetic.Trainer", **trainer},
        "env": {"class": "synthetic.Env", "n_actions": len(ACTIONS), "action_names": ACTIONS, **env},
        "preprocessor": preprocessor,
        "predictors": predictors or {},
        "actor": actor or {"class": "synthetic.Actor", "kind": "free_energy", "n_hidden": 5, "gamma": 0.95},
    }
    (run_dir / "records" / "run.json").write_text(json.dumps(manifest, indent=2))


def _optimal_actions(classes: list[str]) -> np.ndarray:
    return np.array([-1 if CW_OPTIMAL[c] is None else ACTIONS.index(CW_OPTIMAL[c]) for c in classes], dtype=np.int64)


def _greedy_counts(rng, n_runs, noise_levels, optimal, n_images, trained: bool) -> np.ndarray:
    n_actions = len(ACTIONS)
    counts = np.empty((n_runs, len(noise_levels), len(optimal), n_actions), dtype=np.int64)
    for level, noise in enumerate(noise_levels):
        # Trained agents stay accurate up to 37.5 % test noise, then decline (Fig. 3.6(c)).
        p_opt = max(0.25, 0.95 - 1.5 * max(0.0, noise - 0.375)) if trained else 0.25
        for c, a in enumerate(optimal):
            p = np.full(n_actions, 1 / n_actions)
            if a >= 0:
                p = np.full(n_actions, (1 - p_opt) / (n_actions - 1))
                p[a] = p_opt
            counts[:, level, c] = rng.multinomial(n_images, p, size=n_runs)
    return counts


def _action_probs(rng, n_runs, optimal, n_images, trained: bool) -> np.ndarray:
    alpha = np.ones((len(optimal), len(ACTIONS)))
    if trained:
        alpha[optimal >= 0, optimal[optimal >= 0]] = 12.0
    return np.stack(
        [[rng.dirichlet(alpha[c], size=n_images) for c in range(len(optimal))] for _ in range(n_runs)]
    ).astype(np.float32)


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


def make_floor_run(
    run_dir: Path,
    *,
    n_runs: int = 2,
    steps: int = 500,
    n_images: int = 20,
    n_hidden: int = 5,
    classes: list[str] | None = None,
    reward: bool = True,
    probe_noise: float = 0.125,
    seed: int = 0,
    experiment: str = "ch3_floor_synthetic",
) -> Path:
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
    np.savez(records / "steps.npz", rewards=rewards, td_errors=rng.normal(size=(n_runs, steps)).astype(np.float32))

    clean = _clean_images(rng, classes, n_images)
    test = dict(
        noise_levels=noise_levels,
        classes=np.array(classes),
        optimal_action=optimal,
        action_names=np.array(ACTIONS),
        arrangement=ARRANGEMENT.copy(),
        probe_noise=np.float64(probe_noise),
        beta=np.float64(2.0),
        probe_images=_with_noise(rng, clean, probe_noise).astype(np.float16),
        clean_images=clean.astype(np.float16),
    )
    if "N" in classes:
        test["arrangement"] = np.where(ARRANGEMENT == "5", "N", ARRANGEMENT)
    for phase, trained in (("before", False), ("after", reward)):
        test[f"greedy_counts_{phase}"] = _greedy_counts(rng, n_runs, noise_levels, optimal, n_images, trained)
        test[f"probs_{phase}"] = _action_probs(rng, n_runs, optimal, n_images, trained)
        hidden = _hidden(rng, n_runs, optimal, n_images, n_hidden, trained)
        test[f"hidden_{phase}"] = hidden
        test[f"hidden_marginal_{phase}"] = hidden if reward else 0.05 * hidden
    np.savez(records / "floor_test.npz", **test)
    np.savez(
        records / "weights.npz",
        state_weights_before=rng.normal(0, 0.01, (n_runs, PIXELS, n_hidden)).astype(np.float32),
        state_weights_after=rng.normal(0, 0.3, (n_runs, PIXELS, n_hidden)).astype(np.float32),
    )
    write_manifest(
        run_dir,
        "digit_floor",
        experiment,
        {"kind": "continuing", "phases": ["actor", "test"], "steps": steps},
        {
            "kind": "digit_floor",
            "episodic": False,
            "observation": "image",
            "observation_size": PIXELS,
            "noise": probe_noise,
            "reward_condition": "cw" if reward else "none",
            "patches": 1,
            "classes": classes,
            "noise_class": "N",
        },
        actor={"class": "synthetic.Actor", "kind": "free_energy", "n_hidden": n_hidden, "gamma": 0.95},
    )

    scored = optimal >= 0
    after = test["greedy_counts_after"]
    accuracy = after[:, :, scored, optimal[scored]].sum(-1) / after[:, :, scored].sum((-1, -2))
    summary = {
        "experiment": experiment,
        "task": "digit_floor",
        "seeds": list(range(seed, seed + n_runs)),
        "metrics": {
            "reward_per_step_last10pct": rewards[:, -steps // 10 :].mean(axis=1).tolist(),
            "greedy_accuracy": {f"{x:g}": accuracy[:, level].tolist() for level, x in enumerate(noise_levels)},
        },
        "optimal": {"reward_per_step": 8.0},
        "wall_time_s": 1.0,
        "agent_steps_per_s": 1000.0,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    (run_dir / ".hydra").mkdir()
    (run_dir / ".hydra" / "config.yaml").write_text(f"experiment: {experiment}\nseed: {seed}\n")
    (run_dir / "checkpoints").mkdir()
    (run_dir / "checkpoints" / "last.pt").write_bytes(b"synthetic checkpoint")
    (run_dir / "tb").mkdir()
    return run_dir


# ---- T-mazes (chapter 4) ---------------------------------------------------------

TMAZE_OPTIMAL_STEPS, TMAZE_MAX_STEPS, TMAZE_GAMMA = 3, 10, 0.95
TMAZE_OPTIMAL_RETURN = -0.1 - 0.1 * TMAZE_GAMMA + 5 * TMAZE_GAMMA**2  # 4.3175 (CONTRACT §7)
N_OBS = 7
PREDICTOR_FACTS = {  # what a predictor of each kind records in run.json
    "joint": {"predicts_observation": True, "reward_output": "bits"},
    "observation": {"predicts_observation": True, "reward_output": "none"},
    "reward": {"predicts_observation": False, "reward_output": "linear"},
    "other": {"predicts_observation": True, "reward_output": "linear"},  # no dissertation role
}


def _tmaze_episode(rng, success: bool) -> tuple[int, float, float, bool]:
    """(steps, discounted return, terminal reward, correct goal) of one synthetic episode."""
    if success:
        return TMAZE_OPTIMAL_STEPS, TMAZE_OPTIMAL_RETURN, 5.0, True
    steps = int(rng.integers(TMAZE_OPTIMAL_STEPS, TMAZE_MAX_STEPS + 1))
    terminal = -0.1 if steps == TMAZE_MAX_STEPS else -5.0  # cut off, or the wrong goal
    ret = sum(-0.1 * TMAZE_GAMMA**t for t in range(steps - 1))
    ret += terminal * TMAZE_GAMMA ** (steps - 1)
    return steps, ret, terminal, False


def _prediction_errors(rng, n_runs, epochs, lengths, scale: float) -> np.ndarray:
    """Eq. (4.8)-like errors: t = 0 stays high (random signal), later steps fall fast."""
    err = np.full((n_runs, len(epochs), len(lengths), TMAZE_MAX_STEPS + 1), np.nan, np.float32)
    decay = 0.05 + 0.95 * np.exp(-np.asarray(epochs) / 4.0)
    for k, T in enumerate(lengths):
        longer = 1.2 if T > TMAZE_OPTIMAL_STEPS + 4 else 1.0
        err[:, :, k, 0] = 1.0
        err[:, :, k, 1 : T + 1] = 2.0 * scale * longer * decay[None, :, None]
    return err + rng.uniform(0, 0.01, err.shape).astype(np.float32)


def make_tmaze_run(
    run_dir: Path,
    *,
    n_runs: int = 2,
    n_episodes: int = 600,
    matching: bool = True,
    hidden: str = "separable",
    memory_keys: tuple[str, ...] = ("memory_joint",),
    signal_memories: tuple[str, ...] | None = None,
    predictors: dict[str, str] | None = None,
    steps_to_goal: bool = True,
    n_memory: int = 6,
    n_hidden: int = 5,
    seed: int = 0,
    experiment: str | None = None,
    env: dict | None = None,
    preprocessor: dict | None = None,
) -> Path:
    """Write a synthetic T-maze run (docs/records.md, "T-mazes") into `run_dir` and return it.

    `predictors` maps each predictor's name to what it predicts (`PREDICTOR_FACTS`: "joint",
    "observation" or "reward"; default one "joint" predictor, Algorithm 1); `env` adds to or
    overrides the environment's facts in run.json, `preprocessor` names one there.

    The truth: every run becomes optimal by 60 % of the episodes and its TD error decays
    ~100-fold; the memories in `signal_memories` (default: all) encode the initial signal
    from the start, the others are one prototype per run plus noise; the actor's state is
    the junction observation and all memories; the actor's hidden activations at the
    junction are unstructured in the first half of the episodes and one prototype per
    condition (plus small noise) in the second half — unless `hidden` is "shuffled", which
    permutes them across each run's visits (a null control).
    """
    rng = np.random.default_rng(seed)
    experiment = experiment or f"table4_1_{'matching' if matching else 'regular'}_synthetic"
    records = run_dir / "records"
    records.mkdir(parents=True)

    predictors = {"joint": "joint"} if predictors is None else predictors
    lengths = np.arange(TMAZE_OPTIMAL_STEPS, TMAZE_MAX_STEPS + 1)
    epochs = np.arange(0, 41, 2)
    predictor = {}
    for name in predictors:
        predictor |= {
            f"{name}_lengths": lengths,
            f"{name}_epochs": epochs,
            f"{name}_error_train": _prediction_errors(rng, n_runs, epochs, lengths, 1.0),
            f"{name}_error_test": _prediction_errors(rng, n_runs, epochs, lengths, 1.1),
        }
    np.savez(records / "predictor.npz", **predictor)

    n_conditions = 4 if matching else 2
    condition = rng.integers(0, n_conditions, (n_runs, n_episodes))
    success = rng.random((n_runs, n_episodes)) < np.clip(np.linspace(0.2, 1.6, n_episodes), 0, 1)
    steps, ret, terminal, correct = (np.array(x) for x in zip(*[_tmaze_episode(rng, s) for s in success.ravel()]))
    shape = (n_runs, n_episodes)
    td_abs = 2.0 * np.exp(-5.0 * np.arange(n_episodes) / n_episodes) + rng.uniform(0, 0.01, shape)
    sampled = np.arange(0, n_episodes, 50)
    td_sampled = np.full((n_runs, len(sampled), TMAZE_MAX_STEPS), np.nan, np.float32)
    for r in range(n_runs):
        for i, k in enumerate(sampled):
            n = steps.reshape(shape)[r, k]
            td_sampled[r, i, :n] = rng.normal(0, td_abs[r, k], n)
    episodes = dict(
        discounted_return=ret.reshape(shape).astype(np.float32),
        steps=steps.reshape(shape).astype(np.int64),
        terminal_reward=terminal.reshape(shape).astype(np.float32),
        correct_goal=correct.reshape(shape).astype(bool),
        td_abs_mean=td_abs.astype(np.float32),
        condition=condition,
        td_sampled=td_sampled,
        td_sampled_episodes=sampled,
        gamma=np.float64(TMAZE_GAMMA),
        optimal_return=np.float64(TMAZE_OPTIMAL_RETURN),
        optimal_steps=np.float64(TMAZE_OPTIMAL_STEPS),
    )
    np.savez(records / "episodes.npz", **episodes)

    # One junction visit per episode at t = 2; long failed episodes come back once more.
    run_idx, episode_idx = np.indices(shape).reshape(2, -1)
    again = episodes["steps"].ravel() >= 6
    run_idx = np.concatenate([run_idx, run_idx[again]])
    episode_idx = np.concatenate([episode_idx, episode_idx[again]])
    step = np.concatenate([np.full(shape, 2).ravel(), np.full(again.sum(), 3)])
    cond = condition[run_idx, episode_idx]
    initial = cond // 2 if matching else cond
    junction_signal = cond % 2 if matching else np.full_like(cond, -1)
    n_visits = len(cond)

    def noisy(protos: np.ndarray, labels: np.ndarray, sd: float) -> np.ndarray:
        noise = rng.normal(0, sd, (n_visits, protos.shape[2]))
        return np.clip(protos[run_idx, labels] + noise, 0, 1)

    junction = {
        "run": run_idx,
        "episode": episode_idx,
        "step": step,
        "condition": cond,
        "initial_signal": initial,
        "junction_signal": junction_signal,
    }
    if steps_to_goal:
        junction["steps_to_goal"] = episodes["steps"][run_idx, episode_idx]
    for key in memory_keys:
        if signal_memories is None or key in signal_memories:
            junction[key] = noisy(rng.uniform(0.1, 0.9, (n_runs, 2, n_memory)), initial, 0.03)
        else:
            junction[key] = noisy(rng.uniform(0.1, 0.9, (n_runs, 1, n_memory)), np.zeros_like(initial), 0.03)
    obs = np.zeros((n_visits, N_OBS))
    obs[:, 2] = 1.0  # position bit: the T-junction
    if matching:
        obs[np.arange(n_visits), 5 + junction_signal] = 1.0
    junction["state"] = np.concatenate([obs, *(junction[k] for k in memory_keys)], axis=1)
    late = episode_idx >= n_episodes // 2
    acts = np.where(
        late[:, None],
        noisy(rng.uniform(0, 1, (n_runs, n_conditions, n_hidden)), cond, 0.05),
        rng.uniform(0, 1, (n_visits, n_hidden)),
    )
    if hidden == "shuffled":
        for r in range(n_runs):
            mine = np.flatnonzero(run_idx == r)
            acts[mine] = acts[rng.permutation(mine)]
    junction["hidden"] = acts
    np.savez(
        records / "probe.npz",
        **{k: v.astype(np.float16) if v.dtype.kind == "f" else v.astype(np.int64) for k, v in junction.items()},
    )

    last = slice(-200, None)
    final_return = episodes["discounted_return"][:, last].mean(1)
    final_correct = episodes["correct_goal"][:, last].mean(1)
    summary = {
        "experiment": experiment,
        "task": "tmaze",
        "seeds": list(range(seed, seed + n_runs)),
        "metrics": {
            "final_discounted_return": final_return.tolist(),
            "final_steps_to_goal": episodes["steps"][:, last].mean(1).tolist(),
            "final_correct_goal_rate": final_correct.tolist(),
            "solved": ((final_return >= 0.95 * TMAZE_OPTIMAL_RETURN) & (final_correct >= 0.95)).astype(int).tolist(),
        },
        "optimal": {"discounted_return": TMAZE_OPTIMAL_RETURN, "steps_to_goal": TMAZE_OPTIMAL_STEPS},
        "wall_time_s": 1.0,
        "agent_steps_per_s": 1000.0,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    junction_names = ("junction_0", "junction_1") if matching else ("junction",)
    write_manifest(
        run_dir,
        "tmaze",
        experiment,
        {
            "kind": "phased",
            "phases": [*(["preprocessor"] if preprocessor else []), "collect", "predictors", "actor"],
            "l_training": 5,
            "final_window": 200,
            "n_episodes": n_episodes,
        },
        {
            "kind": "tmaze",
            "episodic": True,
            "observation": "bits",
            "observation_size": N_OBS,
            "matching": matching,
            "corridor_length": TMAZE_OPTIMAL_STEPS,
            "max_steps": TMAZE_MAX_STEPS,
            "goal_reward": 5.0,
            "reward_values": [5.0, -5.0, -1.0, -0.1],
            "observation_names": ["start_0", "start_1", "corridor", *junction_names, "goal_left", "goal_right"],
            "labels": ["condition", "initial_signal", "junction_signal"],
            "outcomes": ["correct_goal", "condition"],
            **(env or {}),
        },
        {
            name: {"class": "synthetic.Predictor", "kind": "elman", "memory_size": n_memory, **PREDICTOR_FACTS[kind]}
            for name, kind in predictors.items()
        },
        preprocessor,
        {"class": "synthetic.Actor", "kind": "free_energy", "n_hidden": n_hidden, "gamma": TMAZE_GAMMA},
    )
    (run_dir / "tb").mkdir()
    return run_dir


# ---- T-mazes of chapter 5 (Algorithm 2) -------------------------------------------

CH5_MEMORIES = ("memory_observation", "memory_reward")
# The observations of the matching maze in the order of the environment's observation table,
# with the digit classes of table5_1_pixel: the signals share the digits 0 and 1.
DIGIT_CLASSES = {
    "start_0": 0,
    "start_1": 1,
    "corridor": 2,
    "junction_0": 0,
    "junction_1": 1,
    "goal_left": 3,
    "goal_right": 4,
}


def _preprocessor_records(
    rng, n_runs: int, reservoir_size: int, n_hidden: int, sweeps: int, codes: str
) -> dict[str, np.ndarray]:
    """records/preprocessor.npz: raw images around one binary prototype per digit class, and
    processed codes around one prototype per class and run ("separable") or, "shuffled",
    the same codes permuted across each run's images (a null control)."""
    classes = sorted(set(DIGIT_CLASSES.values()))
    images = _clean_images(rng, [str(c) for c in classes], reservoir_size)  # (C, K, 784)
    protos = rng.uniform(0, 1, (n_runs, len(classes), 1, n_hidden))
    y = np.clip(protos + rng.normal(0, 0.05, (n_runs, len(classes), reservoir_size, n_hidden)), 0, 1)
    if codes == "shuffled":
        flat = y.reshape(n_runs, -1, n_hidden)
        y = np.stack([f[rng.permutation(len(f))] for f in flat]).reshape(y.shape)
    table = [DIGIT_CLASSES[name] for name in DIGIT_CLASSES]
    curve = 0.03 + 0.1 * np.exp(-np.arange(sweeps) / 3.0)
    return dict(
        reconstruction_error=(curve + rng.uniform(0, 0.002, (n_runs, sweeps))).astype(np.float32),
        test_error_before=rng.uniform(0.22, 0.24, n_runs).astype(np.float32),
        test_error_after=rng.uniform(0.03, 0.04, n_runs).astype(np.float32),
        cached=np.bool_(False),
        raw_observations=np.concatenate([images[c] for c in table]).astype(np.float16),
        processed_observations=np.concatenate([y[:, c] for c in table], axis=1).astype(np.float16),
    )


def make_ch5_run(
    run_dir: Path,
    *,
    pixel: bool = True,
    signal_role: str = "reward",
    names: tuple[str, str] = ("observation", "reward"),
    codes: str = "separable",
    reservoir_size: int = 20,
    n_rbm_hidden: int = 8,
    sweeps: int = 12,
    n_runs: int = 2,
    seed: int = 0,
) -> Path:
    """A synthetic chapter-5 run (Algorithm 2): `make_tmaze_run` with an observation and a
    reward predictor named `names`, whose memories keep the initial signal only in the one of
    `signal_role`. With `pixel`, a digit maze (table5_1_pixel: image observations, an RBM
    preprocessor) whose records/preprocessor.npz holds `reservoir_size` images per digit class
    and their processed codes (see `_preprocessor_records`)."""
    experiment = f"table5_1_{'pixel' if pixel else 'bit'}_synthetic"
    roles = dict(zip(("observation", "reward"), names))
    env, preprocessor = {}, None
    if pixel:
        env = {
            "observation": "image",
            "observation_size": PIXELS,
            "digit_classes": DIGIT_CLASSES,
            "reservoir_size": reservoir_size,
        }
        preprocessor = {"class": "synthetic.RBM", "kind": "rbm", "n_visible": PIXELS, "n_hidden": n_rbm_hidden}
    make_tmaze_run(
        run_dir,
        n_runs=n_runs,
        predictors={name: role for role, name in roles.items()},
        memory_keys=tuple(f"memory_{name}" for name in names),
        signal_memories=(f"memory_{roles[signal_role]}",),
        seed=seed,
        experiment=experiment,
        env=env,
        preprocessor=preprocessor,
    )
    if pixel:
        np.savez(
            run_dir / "records" / "preprocessor.npz",
            **_preprocessor_records(
                np.random.default_rng(seed + 1), n_runs, reservoir_size, n_rbm_hidden, sweeps, codes
            ),
        )
    return run_dir


def make_toy_run(run_dir: Path, *, n_episodes: int = 300, n_epochs: int = 5, seed: int = 0) -> Path:
    """A run of a task no chapter knows (`task: toy`): an episodic environment of kind "toy"
    with one boolean outcome (`reached`), one predictor of an unknown kind whose role is none
    of the dissertation's, `episodes.npz` and `predictor.npz`, no junction records. The
    truth: the discounted return of run r is r + episode/n_episodes; |δ| is 1 − episode/n;
    the predictor's error is `n_epochs − epoch` everywhere."""
    rng = np.random.default_rng(seed)
    records = run_dir / "records"
    records.mkdir(parents=True)
    n_runs = 3  # the runs of the summary's metrics below
    progress = np.arange(n_episodes) / n_episodes
    shape = (n_runs, n_episodes)
    np.savez(
        records / "episodes.npz",
        discounted_return=(np.arange(n_runs)[:, None] + progress).astype(np.float32),
        steps=rng.integers(1, 20, shape),
        terminal_reward=rng.normal(size=shape),
        td_abs_mean=np.broadcast_to(1 - progress, shape).astype(np.float32),
        reached=rng.random(shape) < progress,
        gamma=np.float64(0.9),
        optimal_return=np.float64(2.0),
        optimal_steps=np.float64(1.0),
    )
    lengths, epochs = np.arange(2, 5), np.arange(n_epochs + 1)
    error = np.full((n_runs, len(epochs), len(lengths), lengths.max() + 1), np.nan)
    for k, T in enumerate(lengths):
        error[:, :, k, : T + 1] = (n_epochs - epochs)[None, :, None]
    np.savez(
        records / "predictor.npz",
        world_lengths=lengths,
        world_epochs=epochs,
        world_error_train=error.astype(np.float32),
        world_error_test=error.astype(np.float32),
    )
    summary = {
        "experiment": "toy_experiment",
        "task": "toy",
        "seeds": list(range(seed, seed + n_runs)),
        "metrics": {
            "final_return": (np.arange(n_runs) + 1.0).tolist(),
            "score": {"easy": [1.0, 0.5, None], "hard": [0.2, 0.4, 0.9]},
        },
        "wall_time_s": 1.0,
        "agent_steps_per_s": 10.0,
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    write_manifest(
        run_dir,
        "toy",
        "toy_experiment",
        {"kind": "phased", "phases": ["collect", "predictors", "actor"], "n_episodes": n_episodes},
        {"kind": "toy", "episodic": True, "observation": "vector", "observation_size": 3, "outcomes": ["reached"]},
        {
            "world": {
                "class": "tests.ToyPredictor",
                "kind": "toy",
                "predicts_observation": True,
                "reward_output": "linear",
            }
        },
    )
    return run_dir


def load_run(run_dir: Path) -> Run:
    """A synthetic run as the analysis reads it."""
    return Run.load(run_dir, Manifest.load(run_dir))


def assert_analysis_outputs(run_dir: Path, figures, data) -> str:
    """Every figure (as a non-trivial PNG) and data file is in RUN/analysis; returns report.md."""
    out = run_dir / "analysis"
    for name in figures:
        assert (out / f"{name}.png").stat().st_size > 1000, name
    for name in data:
        assert (out / name).is_file(), name
    return (out / "report.md").read_text()
