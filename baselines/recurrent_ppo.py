"""RecurrentPPO on ferl's T-mazes: an external reference baseline for the "Agents side by side" table.

Why: every agent ferl trains is built from the dissertation's parts (RBM actors, Elman or gated
predictors). A standard deep-RL learner with memory, trained end to end on the same registered
Gymnasium ids (CONTRACT §5), tells how hard a maze is outside that family. The learner is
sb3-contrib's RecurrentPPO with ``MlpLstmPolicy`` (Raffin et al. 2021, JMLR 22(268): an LSTM
actor-critic trained by PPO on the sequences of each rollout), the policy-gradient counterpart of
Hausknecht & Stone (2015)'s deep recurrent Q-network (DRQN).

    python baselines/recurrent_ppo.py --env-id ferl/MatchingTMaze-v0 --runs 10 --seed 0 \\
        --steps 60000 --out outputs/baselines/ppo_matching
    python analyze.py outputs/baselines        # a sweep folder: ferl's runs of the same maze beside it

One run = one seed s = seed + r: its own model (``RecurrentPPO(seed=s)``) and ``--n-envs``
environments seeded s·n_envs … s·n_envs + n_envs − 1, so that no two runs share a signal sequence.
Runs go one after the other, not as a batch dimension as train.py's do (CONTRACT §2): the learner
is sb3's. A run trains for ``--steps`` environment steps summed over its environments, rounded up
to whole rollouts (PPO_KWARGS n_steps × n_envs).

``--out`` becomes a run directory that analyze.py reads like a train.py run of a T-maze
(docs/records.md): ``summary.json`` (CONTRACT §2), ``records/run.json`` whose ``env`` is the maze's
own ``describe()`` (so the analysis groups this run with ferl's runs of the same maze),
``records/episodes.npz``, the trained models in ``checkpoints/``, and ``.hydra/overrides.yaml``
with this script's settings in Hydra's override form, by which a sweep report tells jobs apart
(there is no Hydra config). Every finished training episode is recorded as the environment played
it; runs finish different numbers of episodes within the same step budget, and ``episodes.npz``
needs one count for all runs, so every run is cut to the smallest count, and the final-200-episode
metrics and ``solved`` are those of the cut records. There are no TD errors of ferl's kind
(``td_abs_mean`` is NaN, ``td_sampled`` absent). ``env_steps_total`` and ``env_steps_to_solve``
count on the vector environment's clock (every environment's steps, unfinished episodes included),
because the parallel environments' episodes end interleaved.
"""
import argparse
import json
import sys
import time
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
from ferl.envs.tmaze import TMaze
from ferl.run.directory import RunDir, check_run_dir
from ferl.trainers.actor_episodes import final_metrics, sample_efficiency

PROG = "recurrent_ppo.py"
GAMMA = 0.95          # the T-mazes' discount (§4.3.1): returns comparable with ferl's runs and optimum
FINAL_WINDOW = 200    # CONTRACT §2: the tmaze metrics are over the last 200 episodes
RATES = ["correct_goal"]  # the maze's boolean outcome; ``solved`` also asks its rate ≥ 0.95
LSTM_SIZE = 64
# sb3-contrib's RecurrentPPO defaults (n_steps 128, n_epochs 10, gae_lambda 0.95, clip_range 0.2,
# ent_coef 0, vf_coef 0.5, max_grad_norm 0.5), with the RL Zoo's tuned ppo_lstm settings for its
# memory task CartPoleNoVel-v1 (rl-baselines3-zoo hyperparams/ppo_lstm.yml: learning rate linear
# from 1e-3 to 0, batch 256, a 64-unit LSTM for the actor and one for the critic, ReLU heads of 64,
# no orthogonal init). The Zoo's n_steps 32 is not taken: PPO back-propagates through one
# rollout's sequences and starts them from the stored (detached) LSTM state, so an episode cut by a
# rollout's end loses the gradient to its start signal; 128 steps hold whole episodes of the
# corridor-20 maze (T_max 44).
PPO_KWARGS = dict(n_steps=128, batch_size=256, n_epochs=10, gae_lambda=0.95, clip_range=0.2, ent_coef=0.0,
                  vf_coef=0.5, max_grad_norm=0.5, gamma=GAMMA)
LEARNING_RATE = 1e-3  # linearly to 0 over the run (RL Zoo "lin_1e-3")
POLICY_KWARGS = dict(lstm_hidden_size=LSTM_SIZE, enable_critic_lstm=True, net_arch=dict(pi=[64], vf=[64]),
                     activation_fn=torch.nn.ReLU, ortho_init=False)
EPISODE_KEYS = ("discounted_return", "steps", "terminal_reward", "correct_goal", "condition", "env_steps")


def learning_rate(progress_remaining: float) -> float:
    """The RL Zoo's "lin_1e-3": 1e-3 at the start, 0 at the end (a function, as every sb3 ≥ 2.3 takes)."""
    return LEARNING_RATE * progress_remaining


class EpisodeRecorder(BaseCallback):
    """Every finished training episode of every environment, as the environment played it: the
    discounted return Σ_t γ^t r_{t+1}, steps, terminal reward, whether it ended in the rewarded goal
    and its condition (the T-maze view's info at the last step), and the vector environment's step
    count when it ended. sb3 calls ``_on_step`` after each vector step with the raw rewards, before
    PPO adds its bootstrap value to those of truncated episodes."""

    def __init__(self, n_envs: int):
        super().__init__()
        self.returns, self.lengths = np.zeros(n_envs), np.zeros(n_envs, dtype=np.int64)
        self.episodes = {key: [] for key in EPISODE_KEYS}

    def _on_step(self) -> bool:
        rewards, dones, infos = self.locals["rewards"], self.locals["dones"], self.locals["infos"]
        self.returns += GAMMA ** self.lengths * rewards
        self.lengths += 1
        for i in np.flatnonzero(dones):
            info = infos[i]
            if info["steps"] != self.lengths[i]:  # the view counts the episode's actions itself
                raise RuntimeError(f"episode bookkeeping out of step: {self.lengths[i]} ≠ {info['steps']}")
            for key, value in zip(EPISODE_KEYS, (self.returns[i], self.lengths[i], rewards[i], info["correct"],
                                                 info["condition"], self.num_timesteps)):
                self.episodes[key].append(value)
            self.returns[i], self.lengths[i] = 0.0, 0
        return True


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--env-id", required=True, help="a registered ferl T-maze id, e.g. ferl/MatchingTMaze-v0")
    parser.add_argument("--env-kwargs", default="{}", type=json.loads, help='JSON, e.g. \'{"corridor_length": 20}\'')
    parser.add_argument("--runs", type=int, default=10, help="independent runs (seeds seed … seed + runs − 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, required=True, help="environment steps per run")
    parser.add_argument("--out", type=Path, required=True, help="the run directory to write")
    parser.add_argument("--n-envs", type=int, default=8, help="parallel environments per run")
    parser.add_argument("--experiment", default="recurrent_ppo", help="the experiment name in summary.json")
    args = parser.parse_args(argv)
    for name in ("runs", "steps", "n_envs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be ≥ 1, got {getattr(args, name)}")
    if not isinstance(args.env_kwargs, dict):
        parser.error(f"--env-kwargs must be a JSON object, got {args.env_kwargs!r}")
    if check_run_dir(args.out, resume=False) is not None:  # never overwrite an earlier run
        parser.error(f"--out {args.out} already holds a run: pass another directory")
    return args


def fail(message: str) -> None:
    """One line naming what is wrong, exit status 2 (as argparse's usage errors)."""
    print(f"{PROG}: error: {message}", file=sys.stderr)
    sys.exit(2)


def make_maze(env_id: str, kwargs: dict) -> TMaze:
    """The T-maze behind the id (for its description and optimum), made before anything is
    written; ``fail`` if the id or its kwargs do not make one."""
    try:
        view = gymnasium.make(env_id, **kwargs)
    except (gymnasium.error.Error, TypeError, ValueError) as exc:
        fail(f"--env-id {env_id} --env-kwargs {json.dumps(kwargs)}: {exc}")
    maze = getattr(getattr(view.unwrapped, "batch", None), "env", None)
    if not isinstance(maze, TMaze):
        fail(f"--env-id {env_id} is not a ferl T-maze (ferl/TMaze-v0, ferl/MatchingTMaze-v0, "
             "ferl/DigitMatchingTMaze-v0)")
    return maze


def train_run(args, seed: int, checkpoint: Path) -> tuple[dict, int, float]:
    """One run: its episodes (EpisodeRecorder), the environment steps it took and its training time."""
    env = make_vec_env(args.env_id, n_envs=args.n_envs, seed=seed * args.n_envs, env_kwargs=args.env_kwargs)
    batch_size = min(PPO_KWARGS["batch_size"], PPO_KWARGS["n_steps"] * args.n_envs)
    model = RecurrentPPO("MlpLstmPolicy", env, **{**PPO_KWARGS, "batch_size": batch_size},
                         learning_rate=learning_rate, policy_kwargs=POLICY_KWARGS,
                         seed=seed, device="cpu")
    recorder = EpisodeRecorder(args.n_envs)
    started = time.perf_counter()
    model.learn(args.steps, callback=recorder)
    seconds = time.perf_counter() - started
    model.save(checkpoint)
    env.close()
    return recorder.episodes, model.num_timesteps, seconds


def episode_records(runs: list[dict]) -> tuple[dict, np.ndarray]:
    """(R, N) arrays of docs/records.md's episodes.npz, every run cut to the smallest count N; and
    the (R, N) vector-environment step counts at each episode's end."""
    n = min(len(run["steps"]) for run in runs)
    dtypes = {"discounted_return": np.float32, "steps": np.int64, "terminal_reward": np.float32,
              "correct_goal": bool, "condition": np.int64, "env_steps": np.int64}
    cut = {key: np.array([run[key][:n] for run in runs], dtype=dtype) for key, dtype in dtypes.items()}
    env_steps = cut.pop("env_steps")
    cut["td_abs_mean"] = np.full(env_steps.shape, np.nan, dtype=np.float32)  # no TD errors of ferl's kind
    return cut, env_steps


def metrics(records: dict, env_steps: np.ndarray, steps_total: list[int], optimal_return: float) -> dict:
    """CONTRACT §2's tmaze metrics by ferl's own functions; the step counts on the vector
    environment's clock (module doc): all steps taken, and those when the first solved window closed."""
    solved = sample_efficiency(records, np.zeros(len(env_steps), np.int64), optimal_return, FINAL_WINDOW, RATES)
    closing = solved["episodes_to_solve"]
    return {**final_metrics(records, optimal_return, FINAL_WINDOW, RATES),
            "env_steps_total": steps_total,
            "env_steps_to_solve": [None if k is None else int(env_steps[r, k - 1]) for r, k in enumerate(closing)],
            "episodes_to_solve": closing}


def manifest(args, maze: TMaze, n_episodes: int) -> dict:
    """records/run.json (docs/records.md): an external trainer, the maze as ferl describes it, no
    preprocessor or predictors, the LSTM actor-critic as the actor."""
    def plain(value):
        return value.__name__ if isinstance(value, type) else value
    return {"task": maze.task, "experiment": args.experiment,
            "trainer": {"class": "baselines/recurrent_ppo.py", "kind": "external", "phases": ["actor"],
                        "n_episodes": n_episodes, "steps": args.steps, "n_envs": args.n_envs, "env_id": args.env_id,
                        "final_window": FINAL_WINDOW, "library": f"sb3-contrib {SB3_CONTRIB_VERSION}"},
            "env": {"class": f"{type(maze).__module__}.{type(maze).__qualname__}", **maze.describe()},
            "preprocessor": None, "predictors": {},
            "actor": {"class": "sb3_contrib.RecurrentPPO", "kind": "recurrent_ppo", "policy": "MlpLstmPolicy",
                      "n_hidden": LSTM_SIZE, "learning_rate": f"linear {LEARNING_RATE:g} → 0", **PPO_KWARGS,
                      **{key: plain(value) for key, value in POLICY_KWARGS.items()}}}


def overrides(args) -> list[str]:
    """This script's settings as Hydra overrides, without spaces (a sweep report splits on them)."""
    kwargs = [f"env.{key}={json.dumps(value, separators=(',', ':'))}" for key, value in args.env_kwargs.items()]
    return [f"env_id={args.env_id}", *kwargs, f"steps={args.steps}", f"n_envs={args.n_envs}"]


def main(argv=None) -> None:
    """Check the settings and the maze, train the runs one after the other, write the run directory."""
    args = parse_args(argv)
    maze = make_maze(args.env_id, args.env_kwargs)
    torch.set_num_threads(1)  # one core per script: runs of several settings go side by side, one per core
    run = RunDir(args.out)
    seeds = [args.seed + r for r in range(args.runs)]
    started = time.perf_counter()
    runs, steps_total, train_time = [], [], 0.0
    for r, seed in enumerate(seeds):
        episodes, steps, seconds = train_run(args, seed, run.path / "checkpoints" / f"run_{r}.zip")
        runs.append(episodes)
        steps_total.append(steps)
        train_time += seconds
        rate = np.mean(episodes["correct_goal"][-FINAL_WINDOW:]) if episodes["correct_goal"] else float("nan")
        print(f"{PROG}: run {r + 1}/{args.runs} (seed {seed}): {steps} steps in {seconds:.1f} s "
              f"({steps / seconds:.0f} steps/s), {len(episodes['steps'])} episodes, "
              f"correct-goal rate over the last {FINAL_WINDOW} {rate:.3f}", flush=True)
    if min(len(episodes["steps"]) for episodes in runs) == 0:
        fail(f"a run finished no episode in {args.steps} steps: pass a larger --steps")

    records, env_steps = episode_records(runs)
    optimal = maze.optimal(GAMMA)
    run.save_records("episodes", **records, gamma=np.float64(GAMMA),
                     optimal_return=np.float64(optimal["discounted_return"]),
                     optimal_steps=np.float64(maze.optimal_steps))
    run.save_json("run", manifest(args, maze, records["steps"].shape[1]))
    (run.path / ".hydra").mkdir(exist_ok=True)
    OmegaConf.save(OmegaConf.create(overrides(args)), run.path / ".hydra" / "overrides.yaml")
    summary = {"experiment": args.experiment, "task": maze.task, "seeds": seeds,
               "metrics": metrics(records, env_steps, steps_total, optimal["discounted_return"]),
               "optimal": optimal, "wall_time_s": time.perf_counter() - started,
               "agent_steps_per_s": sum(steps_total) / train_time}
    run.write_summary(summary)
    print(f"{PROG}: {args.runs} runs done in {summary['wall_time_s']:.1f} s "
          f"({summary['agent_steps_per_s']:.0f} steps/s), solved {sum(summary['metrics']['solved'])}/{args.runs}\n"
          f"  summary: {run.path / 'summary.json'}")


if __name__ == "__main__":
    main()
