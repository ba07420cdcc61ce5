"""Every agent on every task of the baselines comparison (docs/beyond.md, "Baselines side by side"; `make baselines`), ``--jobs``
at a time, then ``analyze.py`` on the folder: its report's "Agents side by side" section has, per
task, every agent's table row, the finding of which leads, and one learning-curve figure.

Agents (``actor``, ``predictor``; docs/usage.md): the dissertation's FERL agent; memoryless FERL
(``predictor=none``); the recurrent-model architecture with a feed-forward Q-network
(``actor=mlp_q``); a DRQN-style recurrent Q-learner (``actor=drqn predictor=none``, episodic tasks
only); the oracle (``actor=oracle predictor=none``: tabular Q on the true state); and, where
sb3-contrib is installed (``.[baselines]``), RecurrentPPO through the Gymnasium ids.

Tasks: the digit floor (``ch3_floor``; its agent has no memory, so memoryless FERL is FERL
itself, and DRQN needs episodes), the matching T-maze (``table4_1_matching`` with Algorithm 1's
joint predictor and ``table5_1_bit`` with Algorithm 2's separate predictors: one task, two FERL
and two MLP-Q agents; the agents without predictors are the same for both and run once), the
pixel T-maze (``table5_1_pixel``) and the corridor-20 regular T-maze of docs/beyond.md ("Directed exploration") as `make beyond`
runs it (T_max 44, 2 000 episodes for every agent; the agents with predictors trained online:
Algorithm 1's random walks almost never reach a goal 20 cells away, so its collection cannot
balance the episode lengths).

A job whose run directory already holds its finished run is kept, and an interrupted ferl job
resumes from its checkpoint (``resume=true``; ``ferl.run.jobs``), so an interrupted comparison
continues where it stopped when given the same folder (``make baselines RESUME=<folder>``). An
interrupted RecurrentPPO job cannot resume: it is set aside (``<folder>.interrupted``) and starts again.

    python baselines/side_by_side.py outputs/baselines/NAME [--jobs 2] [--only SUBSTRING,…]
"""

import argparse
import importlib.util
import subprocess
import sys
import time
from pathlib import Path

from ferl.run.jobs import DONE, RESUMED, TODO, JobError, job_state, run_commands, states_line

ROOT = Path(__file__).resolve().parents[1]
FLOOR = ["experiment=ch3_floor"]
# §3.5's discount and inverse temperature for the actors whose YAML holds the T-maze values (the
# oracle's too: its table starts at 0, below the floor's positive values, so a near-greedy policy
# would stop trying the actions it has not valued yet: β → 100 gave 7.58 ± 0.20 reward a step)
FLOOR_SCHEDULES = ["actor.gamma=0.9", "actor.beta.end=2"]
MATCHING, BIT, PIXEL = ["experiment=table4_1_matching"], ["experiment=table5_1_bit"], ["experiment=table5_1_pixel"]
CORRIDOR_20 = ["experiment=table4_1_regular", "env.corridor_length=20", "env.max_steps=44", "trainer.n_episodes=2000"]
ONLINE = ["trainer=online", "trainer.replay_sample=16"]  # make beyond's memory-length cell
PPO_STEPS = 60_000  # per run: about the environment steps of Algorithm 1 on the matching maze (54 256)


def train_jobs() -> dict[str, list[str]]:
    """Job name → train.py overrides, longest first so that the parallel lanes end together."""
    jobs = {"pixel/ferl": PIXEL, "pixel/mlp_q": [*PIXEL, "actor=mlp_q"]}
    for name, task in (("corridor20", CORRIDOR_20), ("pixel", PIXEL), ("matching", MATCHING)):
        predicted = [*task, *ONLINE] if task is CORRIDOR_20 else task
        jobs |= {
            f"{name}/ferl": predicted,
            f"{name}/mlp_q": [*predicted, "actor=mlp_q"],
            f"{name}/memoryless": [*task, "predictor=none"],
            f"{name}/drqn": [*task, "actor=drqn", "predictor=none"],
            f"{name}/oracle": [*task, "actor=oracle", "predictor=none", *(["~preprocessor"] if task is PIXEL else [])],
        }
    jobs |= {
        "bit/ferl": BIT,
        "bit/mlp_q": [*BIT, "actor=mlp_q"],
        "floor/ferl": FLOOR,
        "floor/mlp_q": [*FLOOR, "actor=mlp_q", *FLOOR_SCHEDULES],
        "floor/oracle": [*FLOOR, "actor=oracle", *FLOOR_SCHEDULES],
    }
    return jobs


def ppo_jobs() -> dict[str, list[str]]:
    """The external reference, where sb3-contrib is installed."""
    if importlib.util.find_spec("sb3_contrib") is None:
        print("sb3-contrib is not installed (pip install -e '.[baselines]'): no RecurrentPPO reference")
        return {}
    common = ["--runs", "10", "--steps", str(PPO_STEPS)]
    return {
        "ppo/corridor20": [
            "--env-id",
            "ferl/TMaze-v0",
            "--env-kwargs",
            '{"corridor_length": 20, "max_steps": 44}',
            *common,
            "--experiment",
            "table4_1_regular",
        ],
        "ppo/matching": ["--env-id", "ferl/MatchingTMaze-v0", *common, "--experiment", "table4_1_matching"],
    }


def command(name: str, args: list[str], out: Path, ppo: bool) -> list[str]:
    run_dir = out / name.replace("/", "_")
    if ppo:
        return [sys.executable, str(ROOT / "baselines" / "recurrent_ppo.py"), *args, "--out", str(run_dir)]
    # an interrupted job continues from its checkpoint; one stopped before its first starts anew
    resume = ["resume=true"] if (run_dir / "checkpoints").exists() else []
    return [sys.executable, str(ROOT / "train.py"), *args, *resume, f"hydra.run.dir={run_dir}"]


def set_aside(run_dir: Path) -> None:
    """Rename an interrupted RecurrentPPO job (recurrent_ppo.py starts a run anew and never writes
    into a folder that holds one) to ``<name>.interrupted[-k]``: kept, and out of the job's way."""
    aside, k = run_dir.with_name(f"{run_dir.name}.interrupted"), 1
    while aside.exists():
        aside, k = run_dir.with_name(f"{run_dir.name}.interrupted-{k}"), k + 1
    run_dir.rename(aside)
    print(f"ferl: {run_dir.name} was interrupted; RecurrentPPO starts it again (what it wrote: {aside})", flush=True)


def run_table(
    out: Path,
    trains: dict,
    ppos: dict,
    jobs: int,
    only: str = "",
    first: int = 1,
    before_analysis=None,
    analyze: bool = True,
) -> int:
    """Run the jobs ``jobs`` at a time (train.py ones: ``trains``, RecurrentPPO ones: ``ppos``), the
    ``first`` longest train.py jobs, then PPO's, then the rest; one progress line per finished job.
    One first: the two longest (the pixel maze's FERL and MLP-Q) share their fitted RBM and their
    predictors' graphs, which the second then loads from the caches instead of computing them at
    the same time (docs/performance.md, "One compiler of a graph at a time");
    then ``before_analysis(out)`` where given and analyze.py on ``out`` (unless not ``analyze``). Jobs done already are kept,
    interrupted ones resume (``ferl.run.jobs``); exit status 1 if any failed, 2 if a job's folder
    holds another run."""
    order = [*list(trains)[:first], *ppos, *list(trains)[first:]]
    chosen = [n for n in order if any(part in n for part in only.split(","))]
    try:  # a train.py job's overrides are checked against its run's; PPO's .hydra/ holds its own settings
        states = {n: job_state(out / n.replace("/", "_"), trains.get(n)) for n in chosen}
    except JobError as e:
        print(f"ferl: error: {e}", file=sys.stderr)
        return 2
    for name in (n for n in ppos if states.get(n) == RESUMED):  # PPO does not resume: it starts again
        states[name] = TODO
        set_aside(out / name.replace("/", "_"))
    if any(s != TODO for s in states.values()):
        print(f"ferl: resuming {out}: {states_line(list(states.values()))}", flush=True)
    todo = {n: command(n, trains.get(n) or ppos[n], out, n in ppos) for n in chosen if states[n] != DONE}
    started = time.monotonic()
    failed = run_commands(todo, out, jobs)
    (out / "train_wall_time_s").write_text(f"{round(time.monotonic() - started)}\n")
    if failed:
        return 1
    if not analyze:
        return 0
    if before_analysis is not None:
        before_analysis(out)
    return subprocess.run([sys.executable, str(ROOT / "analyze.py"), str(out)], cwd=ROOT).returncode


def arguments(doc: str, stages: tuple[str, ...] = (), flags: dict[str, str] | None = None) -> argparse.Namespace:
    """The scripts' command line: the folder, ``--stage`` where there are ``stages``, ``--jobs``,
    ``--only`` and the yes/no ``flags`` (name → help)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    for flag, text in (flags or {}).items():
        parser.add_argument(flag, action="store_true", help=text)
    if stages:
        parser.add_argument("--stage", choices=stages, default=stages[-1])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--only",
        default="",
        help="run only the jobs whose name contains one of these (comma-separated), e.g. pixel/,floor/oracle",
    )
    return parser.parse_args()


def main() -> int:
    args = arguments(__doc__)
    return run_table(args.out, train_jobs(), ppo_jobs(), args.jobs, args.only)


if __name__ == "__main__":
    sys.exit(main())
