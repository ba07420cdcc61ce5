"""RecurrentPPO on ferl's T-mazes and on any Gymnasium id with discrete actions: an external
reference baseline for the "Agents side by side" table.

Why: every agent ferl trains is built from the dissertation's parts (RBM actors, Elman or gated
predictors). A standard deep-RL learner with memory, trained end to end on the same registered
Gymnasium ids (docs/usage.md, "Environments for other agents"), tells how hard a task is outside that family. The learner is
sb3-contrib's RecurrentPPO with ``MlpLstmPolicy`` (Raffin et al. 2021, JMLR 22(268): an LSTM
actor-critic trained by PPO on the sequences of each rollout), the policy-gradient counterpart of
Hausknecht & Stone (2015)'s deep recurrent Q-network (DRQN).

    python baselines/recurrent_ppo.py --env-id ferl/MatchingTMaze-v0 --runs 10 --seed 0 \\
        --steps 60000 --out outputs/baselines/ppo_matching
    python baselines/recurrent_ppo.py --env-id popgym:popgym-RepeatPreviousEasy-v0 --gamma 0.99 \\
        --optimal-return 1 --steps 1000000 --out outputs/baselines/ppo_repeat_previous
    python analyze.py outputs/baselines        # a sweep folder: ferl's runs of the same task beside it

Two kinds of ``--env-id``. ferl's own ids (``ferl/…``) must name a T-maze (``ferl/TMaze-v0``,
``ferl/MatchingTMaze-v0``, ``ferl/DigitMatchingTMaze-v0``): their task is "tmaze". Any other id, or
``module:Id`` (the module is imported and registers it), is read as ferl's ``env=gymnasium`` reads
it (``ferl.envs.gymnasium_vector.GymnasiumEnv``): discrete actions (Discrete or MultiDiscrete),
observations encoded as the bits ferl's agents see (``--encoding``, ``--thresholds``;
``ferl.envs.encodings.BinaryObservation``), episodes cut after the id's own limit or
``--max-steps`` (a ``TimeLimit`` where the registration states none, so that episodes always
end), ``--optimal-return`` and ``--success-threshold`` as ferl's ``env.optimal_return`` and
``env.success_threshold``; its task is "gymnasium". PPO learns from the environment's raw rewards
(ferl's ``reward_scale`` is a view of the task and is not applied). An id that is not registered,
has continuous actions or observations with no encoding is refused in one line before anything
is written.

One run = one seed s = seed + r: its own model (``RecurrentPPO(seed=s)``) and ``--n-envs``
environments seeded s·n_envs … s·n_envs + n_envs − 1, so that no two runs share a signal sequence.
Runs go one after the other, not as a batch dimension as train.py's do (docs/usage.md, "Training"): the learner
is sb3's. A run trains for ``--steps`` environment steps summed over its environments, rounded up
to whole rollouts (PPO_KWARGS n_steps × n_envs). ``--gamma`` is PPO's discount and that of the
recorded discounted returns (0.95, the T-mazes'; POPGym's own PPO used 0.99).

``--out`` becomes a run directory that analyze.py reads like a train.py run of the same task
(docs/records.md): ``summary.json`` (docs/records.md), ``records/run.json`` whose ``env`` is the one
ferl's runs describe (the maze's or ``GymnasiumEnv``'s ``describe()``, so the analysis groups
this run with ferl's runs of the same task), ``records/episodes.npz``, the trained models in
``checkpoints/``, and ``.hydra/overrides.yaml`` with this script's settings in Hydra's override
form, by which a sweep report tells jobs apart (there is no Hydra config). Every finished training
episode is recorded as the environment played it; runs finish different numbers of episodes within
the same step budget, and ``episodes.npz`` needs one count for all runs, so every run is cut to
the smallest count, and the final-window metrics (the last ``--final-window`` episodes, 200 as
ferl's trainers) and ``solved`` are those of the cut records.
A Gymnasium id's records add the undiscounted ``return`` (``final_return``) and, given a success
threshold, ``success``; its ``solved`` needs ``--optimal-return``. There are no TD errors of
ferl's kind (``td_abs_mean`` is NaN, ``td_sampled`` absent). ``env_steps_total`` and
``env_steps_to_solve`` count on the vector environment's clock (every environment's steps,
unfinished episodes included), because the parallel environments' episodes end interleaved.
"""

import argparse
import json
import re
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium
import numpy as np
import torch
from omegaconf import OmegaConf
from sb3_contrib import RecurrentPPO
from sb3_contrib import __version__ as SB3_CONTRIB_VERSION
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

import ferl.envs  # noqa: F401 — registers the ferl/ ids
from ferl.envs.encodings import ENCODINGS, BinaryObservation
from ferl.envs.gymnasium_vector import GymnasiumEnv, make
from ferl.envs.tmaze import TMaze
from ferl.run.directory import RunDir, check_run_dir
from ferl.stats import FINAL_WINDOW, final_metrics, has_goal, sample_efficiency, solved_against

PROG = "recurrent_ppo.py"
GAMMA = 0.95  # the T-mazes' discount (§4.3.1): returns comparable with ferl's runs and optimum
LSTM_SIZE = 64
# sb3-contrib's RecurrentPPO defaults (n_steps 128, n_epochs 10, gae_lambda 0.95, clip_range 0.2,
# ent_coef 0, vf_coef 0.5, max_grad_norm 0.5), with the RL Zoo's tuned ppo_lstm settings for its
# memory task CartPoleNoVel-v1 (rl-baselines3-zoo hyperparams/ppo_lstm.yml: learning rate linear
# from 1e-3 to 0, batch 256, a 64-unit LSTM for the actor and one for the critic, ReLU heads of 64,
# no orthogonal init). The Zoo's n_steps 32 is not taken: PPO back-propagates through one
# rollout's sequences and starts them from the stored (detached) LSTM state, so an episode cut by a
# rollout's end loses the gradient to its start signal; 128 steps hold whole episodes of the
# corridor-20 maze (T_max 44). The discount is ``--gamma``.
PPO_KWARGS = dict(
    n_steps=128,
    batch_size=256,
    n_epochs=10,
    gae_lambda=0.95,
    clip_range=0.2,
    ent_coef=0.0,
    vf_coef=0.5,
    max_grad_norm=0.5,
)
LEARNING_RATE = 1e-3  # linearly to 0 over the run (RL Zoo "lin_1e-3")
POLICY_KWARGS = dict(
    lstm_hidden_size=LSTM_SIZE,
    enable_critic_lstm=True,
    net_arch=dict(pi=[64], vf=[64]),
    activation_fn=torch.nn.ReLU,
    ortho_init=False,
)
# episodes.npz's records (docs/records.md) besides td_abs_mean, with their types
COMMON_RECORDS = {"discounted_return": np.float32, "steps": np.int64, "terminal_reward": np.float32}
TMAZE_RECORDS = {**COMMON_RECORDS, "correct_goal": bool, "condition": np.int64}
# the Gymnasium-only settings, by the name of ferl's env.* config key they mirror
GYMNASIUM_OPTIONS = {
    "encoding": "auto",
    "thresholds": None,
    "max_steps": None,
    "optimal_return": None,
    "success_threshold": None,
}


@dataclass
class Task:
    """What the script needs of the environment beyond PPO: ``env`` (the maze, or a closed
    ``GymnasiumEnv`` of one run) for its task, ``describe()``, ``optimal(γ)`` and ``optimal_steps``;
    what ``make_vec_env`` makes; the episodes.npz records; which records give rates (booleans:
    ``final_<name>_rate``) and averages (``final_<name>``); and the facts of a finished episode
    taken from its last step's info and its undiscounted return."""

    env: object
    make: str | Callable
    env_kwargs: dict | None
    records: dict
    rates: list
    facts: Callable[[dict, float], dict]
    averages: list = field(default_factory=list)


def learning_rate(progress_remaining: float) -> float:
    """The RL Zoo's "lin_1e-3": 1e-3 at the start, 0 at the end (a function, as every sb3 ≥ 2.3 takes)."""
    return LEARNING_RATE * progress_remaining


class EpisodeRecorder(BaseCallback):
    """Every finished training episode of every environment, as the environment played it: the
    undiscounted return, the discounted return Σ_t γ^t r_{t+1}, steps, terminal reward, the task's
    facts (``Task.facts``) and the vector environment's step count when it ended. sb3 calls
    ``_on_step`` after each vector step with the raw rewards, before PPO adds its bootstrap value
    to those of truncated episodes."""

    def __init__(self, n_envs: int, gamma: float, facts: Callable[[dict, float], dict]):
        super().__init__()
        self.gamma, self.facts = gamma, facts
        self.sums, self.returns = np.zeros(n_envs), np.zeros(n_envs)
        self.lengths = np.zeros(n_envs, dtype=np.int64)
        self.episodes = defaultdict(list)

    def _on_step(self) -> bool:
        rewards, dones, infos = self.locals["rewards"], self.locals["dones"], self.locals["infos"]
        self.sums += rewards
        self.returns += self.gamma**self.lengths * rewards
        self.lengths += 1
        for i in np.flatnonzero(dones):
            info = infos[i]
            if info["episode"]["l"] != self.lengths[i]:  # sb3's Monitor counts the episode's steps itself
                raise RuntimeError(f"episode bookkeeping out of step: {self.lengths[i]} ≠ {info['episode']['l']}")
            episode = {
                "return": self.sums[i],
                "discounted_return": self.returns[i],
                "steps": self.lengths[i],
                "terminal_reward": rewards[i],
                **self.facts(info, self.sums[i]),
                "env_steps": self.num_timesteps,
            }
            for key, value in episode.items():
                self.episodes[key].append(value)
            self.sums[i], self.returns[i], self.lengths[i] = 0.0, 0.0, 0
        return True


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--env-id",
        required=True,
        help="a ferl T-maze id (ferl/MatchingTMaze-v0), or any Gymnasium id with discrete actions, "
        "as Id or module:Id (popgym:popgym-RepeatPreviousEasy-v0)",
    )
    parser.add_argument("--env-kwargs", default="{}", type=json.loads, help="JSON, e.g. '{\"corridor_length\": 20}'")
    parser.add_argument("--runs", type=int, default=10, help="independent runs (seeds seed … seed + runs − 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, required=True, help="environment steps per run")
    parser.add_argument("--out", type=Path, required=True, help="the run directory to write")
    parser.add_argument("--n-envs", type=int, default=8, help="parallel environments per run")
    parser.add_argument("--experiment", default="recurrent_ppo", help="the experiment name in summary.json")
    parser.add_argument("--gamma", type=float, default=GAMMA, help="PPO's discount and the records' (POPGym: 0.99)")
    parser.add_argument(
        "--final-window",
        type=int,
        default=FINAL_WINDOW,
        help="episodes behind the final_* metrics (ferl's trainer.final_window)",
    )
    gym = parser.add_argument_group("Gymnasium ids (as ferl's env=gymnasium)")
    gym.add_argument(
        "--encoding", default="auto", choices=ENCODINGS, help="observations → bits (ferl/envs/encodings.py)"
    )
    gym.add_argument("--thresholds", type=json.loads, help="--encoding thresholds: a JSON list, e.g. '[0, 0.5]'")
    gym.add_argument("--max-steps", type=int, help="the episode limit T_max (default: the id's own)")
    gym.add_argument("--optimal-return", type=float, help="the stated optimum of the undiscounted return (solved)")
    gym.add_argument("--success-threshold", type=float, help="an episode whose return exceeds it is a success")
    args = parser.parse_args(argv)
    for name in ("runs", "steps", "n_envs", "final_window"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be ≥ 1, got {getattr(args, name)}")
    if not isinstance(args.env_kwargs, dict):
        parser.error(f"--env-kwargs must be a JSON object, got {args.env_kwargs!r}")
    if not 0 < args.gamma <= 1:
        parser.error(f"--gamma must be in (0, 1], got {args.gamma}")
    if check_run_dir(args.out, resume=False) is not None:  # never overwrite an earlier run
        parser.error(f"--out {args.out} already holds a run: pass another directory")
    return args


def fail(message: str) -> None:
    """One line naming what is wrong, exit status 2 (as argparse's usage errors)."""
    print(f"{PROG}: error: {' '.join(message.splitlines())}", file=sys.stderr)
    sys.exit(2)


def as_options(message: str) -> str:
    """A GymnasiumEnv error in this script's terms: ferl's env.id, env.max_steps … are --env-id,
    --max-steps … here."""
    return re.sub(r"\benv\.(\w+)", lambda m: "--env-id" if m[1] == "id" else "--" + m[1].replace("_", "-"), message)


def make_task(args) -> Task:
    """The task behind --env-id (module docstring), made before anything is written."""
    if args.env_id.startswith("ferl/"):
        return tmaze_task(args)
    return gymnasium_task(args)


def tmaze_task(args) -> Task:
    """A ferl T-maze: ``fail`` if the id or its kwargs do not make one, or a Gymnasium-only option is set."""
    given = [name for name, default in GYMNASIUM_OPTIONS.items() if getattr(args, name) != default]
    if given:
        fail(f"--{given[0].replace('_', '-')} is for Gymnasium ids; ferl's T-maze {args.env_id} states its own")
    try:
        view = gymnasium.make(args.env_id, **args.env_kwargs)
    except (gymnasium.error.Error, TypeError, ValueError) as exc:
        fail(f"--env-id {args.env_id} --env-kwargs {json.dumps(args.env_kwargs)}: {exc}")
    maze = getattr(getattr(view.unwrapped, "batch", None), "env", None)
    if not isinstance(maze, TMaze):
        fail(
            f"--env-id {args.env_id} is not a ferl T-maze (ferl/TMaze-v0, ferl/MatchingTMaze-v0, "
            "ferl/DigitMatchingTMaze-v0)"
        )
    return Task(
        maze,
        args.env_id,
        args.env_kwargs,
        TMAZE_RECORDS,
        rates=["correct_goal"],
        facts=lambda info, ret: {"correct_goal": info["correct"], "condition": info["condition"]},
    )


def gymnasium_task(args) -> Task:
    """Any other id, checked and described by ferl's own ``GymnasiumEnv`` (one run, closed at
    once); ``fail`` with its one line if ferl could not train on it either."""
    try:
        env = GymnasiumEnv(
            1,
            torch.Generator(),
            args.seed,
            id=args.env_id,
            kwargs=args.env_kwargs,
            encoding=args.encoding,
            thresholds=args.thresholds,
            max_steps=args.max_steps,
            success_threshold=args.success_threshold,
            optimal_return=args.optimal_return,
        )
    except (ValueError, TypeError) as exc:  # ConfigError is a ValueError
        fail(as_options(str(exc)))
    env.close()
    threshold = args.success_threshold
    records = {**COMMON_RECORDS, "return": np.float32, **({"success": bool} if threshold is not None else {})}
    return Task(
        env,
        gymnasium_maker(args, env.max_steps, env.thresholds),  # typed, or derived at its set-up (a Box)
        None,
        records,
        rates=["success"] if threshold is not None else [],
        averages=["return"],
        facts=lambda info, ret: {"success": ret > threshold} if threshold is not None else {},
    )


def gymnasium_maker(args, max_steps: int, thresholds: list) -> Callable[[], gymnasium.Env]:
    """One environment as ferl's GymnasiumEnv plays it: its episodes cut after ``max_steps`` (a
    ``TimeLimit`` where the registration states no limit, or a longer one), its observations the
    bits ferl's agents see (``thresholds``: GymnasiumEnv's own, derived where a Box had none)."""
    env_id, kwargs, encoding = args.env_id, args.env_kwargs, args.encoding

    def make_one():
        env = make(env_id, kwargs)
        registered = env.spec.max_episode_steps if env.spec is not None else None
        if registered is None or registered > max_steps:
            env = gymnasium.wrappers.TimeLimit(env, max_episode_steps=max_steps)
        return BinaryObservation(env, encoding, thresholds or ())

    return make_one


def train_run(args, task: Task, seed: int, checkpoint: Path) -> tuple[dict, int, float]:
    """One run: its episodes (EpisodeRecorder), the environment steps it took and its training time."""
    env = make_vec_env(task.make, n_envs=args.n_envs, seed=seed * args.n_envs, env_kwargs=task.env_kwargs)
    batch_size = min(PPO_KWARGS["batch_size"], PPO_KWARGS["n_steps"] * args.n_envs)
    model = RecurrentPPO(
        "MlpLstmPolicy",
        env,
        **{**PPO_KWARGS, "batch_size": batch_size},
        gamma=args.gamma,
        learning_rate=learning_rate,
        policy_kwargs=POLICY_KWARGS,
        seed=seed,
        device="cpu",
    )
    recorder = EpisodeRecorder(args.n_envs, args.gamma, task.facts)
    started = time.perf_counter()
    model.learn(args.steps, callback=recorder)
    seconds = time.perf_counter() - started
    model.save(checkpoint)
    env.close()
    return recorder.episodes, model.num_timesteps, seconds


def progress(task: Task, episodes: dict, window: int) -> str:
    """How a run ended, for its progress line: the T-maze's correct-goal rate, else the mean return,
    over its last ``window`` episodes."""
    name, label = ("correct_goal", "correct-goal rate") if "correct_goal" in task.rates else ("return", "mean return")
    value = np.mean(episodes[name][-window:]) if episodes[name] else float("nan")
    return f"{label} over the last {window} {value:.3f}"


def episode_records(task: Task, runs: list[dict]) -> tuple[dict, np.ndarray]:
    """(R, N) arrays of docs/records.md's episodes.npz, every run cut to the smallest count N; and
    the (R, N) vector-environment step counts at each episode's end."""
    n = min(len(run["steps"]) for run in runs)
    cut = {key: np.array([run[key][:n] for run in runs], dtype=dtype) for key, dtype in task.records.items()}
    env_steps = np.array([run["env_steps"][:n] for run in runs], dtype=np.int64)
    cut["td_abs_mean"] = np.full(env_steps.shape, np.nan, dtype=np.float32)  # no TD errors of ferl's kind
    return cut, env_steps


def metrics(
    task: Task, records: dict, env_steps: np.ndarray, steps_total: list[int], optimal: dict, window: int
) -> dict:
    """The episodic metrics of ``summary.json`` (docs/records.md) by ferl's own functions, over the last ``window`` episodes;
    the step counts on the vector environment's clock (module doc): all steps taken and, given an
    optimum, those when the first solved window closed."""
    optimum = solved_against(optimal)
    finals = final_metrics(records, optimum, window, task.rates, task.averages, goal=has_goal(optimal))
    result = {**finals, "env_steps_total": steps_total}
    if optimum is not None:
        solved = sample_efficiency(records, np.zeros(len(env_steps), np.int64), optimum, window, task.rates)
        closing = solved["episodes_to_solve"]
        result["env_steps_to_solve"] = [None if k is None else int(env_steps[r, k - 1]) for r, k in enumerate(closing)]
        result["episodes_to_solve"] = closing
    return result


def manifest(args, task: Task, n_episodes: int) -> dict:
    """records/run.json (docs/records.md): an external trainer, the environment as ferl describes
    it, no preprocessor or predictors, the LSTM actor-critic as the actor."""

    def plain(value):
        return value.__name__ if isinstance(value, type) else value

    env = task.env
    return {
        "task": env.task,
        "experiment": args.experiment,
        "trainer": {
            "class": "baselines/recurrent_ppo.py",
            "kind": "external",
            "phases": ["actor"],
            "n_episodes": n_episodes,
            "steps": args.steps,
            "n_envs": args.n_envs,
            "env_id": args.env_id,
            "final_window": args.final_window,
            "library": f"sb3-contrib {SB3_CONTRIB_VERSION}",
        },
        "env": {"class": f"{type(env).__module__}.{type(env).__qualname__}", **env.describe()},
        "preprocessor": None,
        "predictors": {},
        "actor": {
            "class": "sb3_contrib.RecurrentPPO",
            "kind": "recurrent_ppo",
            "policy": "MlpLstmPolicy",
            "n_hidden": LSTM_SIZE,
            "learning_rate": f"linear {LEARNING_RATE:g} → 0",
            **PPO_KWARGS,
            "gamma": args.gamma,
            **{key: plain(value) for key, value in POLICY_KWARGS.items()},
        },
    }


def overrides(args) -> list[str]:
    """This script's settings as Hydra overrides, without spaces (a sweep report splits on them);
    the Gymnasium options and --gamma only where they differ from their defaults, named as ferl's
    config names them."""

    def value(x):
        return json.dumps(x, separators=(",", ":"))

    kwargs = [f"env.{key}={value(v)}" for key, v in args.env_kwargs.items()]
    options = [(key, getattr(args, key)) for key, default in GYMNASIUM_OPTIONS.items() if getattr(args, key) != default]
    options = [f"env.{key}={v if isinstance(v, str) else value(v)}" for key, v in options]  # an encoding: a bare word
    gamma = [f"gamma={args.gamma:g}"] if args.gamma != GAMMA else []
    return [f"env_id={args.env_id}", *kwargs, *options, f"steps={args.steps}", f"n_envs={args.n_envs}", *gamma]


def write_run(args, task: Task, run: RunDir, runs: list[dict], steps_total: list[int]) -> dict:
    """episodes.npz, run.json and the overrides of the finished runs; their metrics."""
    records, env_steps = episode_records(task, runs)
    optimal = task.env.optimal(args.gamma)
    run.save_records(
        "episodes",
        len(runs),
        **records,
        gamma=np.float64(args.gamma),
        optimal_return=np.float64(optimal.get("discounted_return", np.nan)),
        optimal_steps=np.float64(task.env.optimal_steps),
        final_window=np.int64(args.final_window),
    )
    run.save_json("run", manifest(args, task, records["steps"].shape[1]))
    (run.path / ".hydra").mkdir(exist_ok=True)
    OmegaConf.save(OmegaConf.create(overrides(args)), run.path / ".hydra" / "overrides.yaml")
    return {"metrics": metrics(task, records, env_steps, steps_total, optimal, args.final_window), "optimal": optimal}


def main(argv=None) -> None:
    """Check the settings and the task, train the runs one after the other, write the run directory."""
    args = parse_args(argv)
    task = make_task(args)
    torch.set_num_threads(1)  # one core per script: runs of several settings go side by side, one per core
    run = RunDir(args.out)
    seeds = [args.seed + r for r in range(args.runs)]
    started = time.perf_counter()
    runs, steps_total, train_time = [], [], 0.0
    for r, seed in enumerate(seeds):
        episodes, steps, seconds = train_run(args, task, seed, run.path / "checkpoints" / f"run_{r}.zip")
        runs.append(episodes)
        steps_total.append(steps)
        train_time += seconds
        print(
            f"{PROG}: run {r + 1}/{args.runs} (seed {seed}): {steps} steps in {seconds:.1f} s "
            f"({steps / seconds:.0f} steps/s), {len(episodes['steps'])} episodes, "
            f"{progress(task, episodes, args.final_window)}",
            flush=True,
        )
    if min(len(episodes["steps"]) for episodes in runs) == 0:
        fail(f"a run finished no episode in {args.steps} steps: pass a larger --steps")

    written = write_run(args, task, run, runs, steps_total)
    summary = {
        "experiment": args.experiment,
        "task": task.env.task,
        "seeds": seeds,
        **written,
        "wall_time_s": time.perf_counter() - started,
        "agent_steps_per_s": sum(steps_total) / train_time,
    }
    run.write_summary(summary)
    solved = summary["metrics"].get("solved")
    print(
        f"{PROG}: {args.runs} runs done in {summary['wall_time_s']:.1f} s "
        f"({summary['agent_steps_per_s']:.0f} steps/s), "
        + (f"solved {sum(solved)}/{args.runs}" if solved is not None else "no optimum stated (no solved)")
        + f"\n  summary: {run.path / 'summary.json'}"
    )


if __name__ == "__main__":
    main()
