"""The Gymnasium suites' own step rate (the limit of ``make suites``) beside ferl's environment.

    python benchmarks/bench_suites.py [--steps 3000] [--runs 10] [--ids ID ...]

For each environment of ``make suites`` (POPGym's Easy RepeatPrevious, CountRecall, Autoencode and
MineSweeper, MiniGrid's MemoryS7), environment steps per second with uniformly random actions
drawn beforehand, so that only the environments are timed:

* ``one env``: one ``gymnasium.make`` environment, reset when its episode ends;
* ``sync ×R`` / ``async ×R``: R of them as one ``gymnasium.vector`` environment (``SyncVectorEnv``;
  ``AsyncVectorEnv``, one subprocess each, without shared memory for MiniGrid, whose mission space
  has none), next-step auto-reset, steps counted over all R;
* ``ferl ×R``: ferl's ``env=gymnasium`` (``ferl.envs.gymnasium_vector.GymnasiumEnv``, sync), its
  observation encoding, ids and boundary checks included, reset when every run has ended (ferl's
  lockstep episodes), steps counted over the runs still in their episode.

Prints a table and merges it into benchmarks/results.json under "suites_env_rate".
"""

import argparse
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import save_results  # noqa: E402
from ferl.envs.gymnasium_vector import GymnasiumEnv, make  # noqa: E402

SUITES = (
    "popgym:popgym-RepeatPreviousEasy-v0",
    "popgym:popgym-CountRecallEasy-v0",
    "popgym:popgym-AutoencodeEasy-v0",
    "popgym:popgym-MineSweeperEasy-v0",
    "minigrid:MiniGrid-MemoryS7-v0",
)


def one_env(env_id: str, steps: int, rng: np.random.Generator) -> float:
    """Steps/s of one environment under random actions."""
    env = make(env_id, {})
    env.action_space.seed(int(rng.integers(2**31)))
    actions = [env.action_space.sample() for _ in range(steps)]
    env.reset(seed=0)
    started = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - started)
    env.close()
    return rate


def vector_env(env_id: str, steps: int, runs: int, kind: str, rng: np.random.Generator) -> float:
    """Environment steps/s (over all runs) of ``runs`` environments as one vector environment (an
    ``AsyncVectorEnv`` without shared memory where the observation space has none, MiniGrid's)."""
    fns = [lambda: make(env_id, {}) for _ in range(runs)]
    mode = gymnasium.vector.AutoresetMode.NEXT_STEP
    if kind == "sync":
        vector = gymnasium.vector.SyncVectorEnv(fns, autoreset_mode=mode)
    else:
        try:
            vector = gymnasium.vector.AsyncVectorEnv(fns, autoreset_mode=mode)
        except ValueError:  # "shared_memory=True caused an error"
            vector = gymnasium.vector.AsyncVectorEnv(fns, autoreset_mode=mode, shared_memory=False)
    vector.action_space.seed(int(rng.integers(2**31)))
    actions = [vector.action_space.sample() for _ in range(steps // runs)]
    vector.reset(seed=list(range(runs)))
    started = time.perf_counter()
    for a in actions:
        vector.step(a)
    rate = len(actions) * runs / (time.perf_counter() - started)
    vector.close()
    return rate


def ferl_env(env_id: str, steps: int, runs: int, rng: np.random.Generator) -> float:
    """Environment steps/s of ferl's ``env=gymnasium`` (runs still in their episode)."""
    env = GymnasiumEnv(runs, torch.Generator(), 0, env_id)
    actions = torch.from_numpy(rng.integers(env.n_actions, size=(steps, runs)))
    env.reset()
    taken, started = 0, time.perf_counter()
    for a in actions:
        taken += int((~env.done).sum())
        env.step(a)
        if bool(env.done.all()):
            env.reset()
        if taken >= steps:
            break
    rate = taken / (time.perf_counter() - started)
    env.vector.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000, help="environment steps timed per row")
    parser.add_argument("--runs", type=int, default=10, help="R: the vector environments' size")
    parser.add_argument("--ids", nargs="+", default=list(SUITES))
    args = parser.parse_args()
    rng, rows = np.random.default_rng(0), []
    print(
        f"{'environment':42s} {'one env':>9s} {f'sync ×{args.runs}':>9s} {f'async ×{args.runs}':>9s} {f'ferl ×{args.runs}':>9s}"
    )
    for env_id in args.ids:
        row = {
            "id": env_id,
            "one_env": one_env(env_id, args.steps, rng),
            "sync": vector_env(env_id, args.steps, args.runs, "sync", rng),
            "async": vector_env(env_id, args.steps, args.runs, "async", rng),
            "ferl": ferl_env(env_id, args.steps, args.runs, rng),
        }
        rows.append(row)
        rates = (row[k] for k in ("one_env", "sync", "async", "ferl"))
        print(f"{env_id:42s} " + " ".join(f"{r:9.0f}" for r in rates), flush=True)
    save_results(ROOT / "benchmarks" / "results.json", "suites_env_rate", "cpu", runs=args.runs, rows=rows)


if __name__ == "__main__":
    main()
