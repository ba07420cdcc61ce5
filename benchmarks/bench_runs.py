"""Agent-steps per second against the number of runs, for the trainers built after the fast path.

    python benchmarks/bench_runs.py [--runs 1 10 100 1000] [--agents recurrent_q online]
                                    [--paths eager compiled] [--budget EPISODES]

Each cell is one ``train.py`` job in a subprocess, its rate read from ``summary.json``'s
``agent_steps_per_s`` (it leaves out the compiled functions' first calls, ``compile_time_s``).
Runs are a batch dimension, so the rate should grow with R until the arithmetic, not the
per-operation overhead, sets it. The episodes of a job shrink as R grows
(``budget // R``, at least ``MIN_EPISODES``; ``BUDGET`` per agent unless ``--budget`` is given), so
that the cells of an agent play about as many agent-episodes:

* ``recurrent_q``: the recurrent Q-learner (DRQN: GRU core, linear head) on the matching
  T-maze, one replay step of 10 sampled episodes after each episode (docs/performance.md);
* ``online``: the online trainer's FERL on the regular T-maze at corridor 20 with an LSTM
  predictor, 64 replayed episodes a step: the bar's configuration. Its replay compiles only in
  jobs of at least ``REPLAY_FUSED_FROM`` episodes (its episodes never), so a shorter job's
  compiled cell would be the eager path again, and is not run.

A compiled job with a fresh shape compiles first (``compile_time_s``, printed beside). Prints a
markdown table and merges it into benchmarks/results.json under "runs_scaling".
"""

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import train_summary  # noqa: E402
from benchmarks.report import save_results  # noqa: E402
from ferl.trainers.online_episodes import REPLAY_FUSED_FROM  # noqa: E402

AGENTS = {
    "recurrent_q": [
        "experiment=table4_1_matching",
        "actor=drqn",
        "predictor=none",
        "trainer.n_sample=10",
    ],
    "online": [
        "experiment=table4_1_regular",
        "trainer=online",
        "env.corridor_length=20",
        "env.max_steps=44",
        "predictor.joint.memory=lstm",
    ],
}
COMPILES_FROM = {"recurrent_q": 1, "online": REPLAY_FUSED_FROM}  # a job's episodes from which it compiles
BUDGET = {"recurrent_q": 2000, "online": 400}  # agent-episodes a cell plays: ~1 min a cell eagerly at 1 run
MIN_EPISODES = 10


def job(agent: str, runs: int, episodes: int, compiled: bool, out: Path) -> dict:
    """One train.py job; its summary's rate, wall and compile seconds."""
    command = [
        sys.executable,
        str(ROOT / "train.py"),
        *AGENTS[agent],
        f"n_runs={runs}",
        f"trainer.n_episodes={episodes}",
        f"compile={str(compiled).lower()}",
        f"hydra.run.dir={out}",
    ]
    summary = train_summary(command, out, f"bench_runs.py: {agent} at {runs} runs")
    return {
        "agent": agent,
        "runs": runs,
        "episodes": episodes,
        "path": "compiled" if compiled else "eager",
        "agent_steps_per_s": summary["agent_steps_per_s"],
        "wall_time_s": summary["wall_time_s"],
        "compile_time_s": summary.get("compile_time_s", 0.0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 10, 100, 1000])
    parser.add_argument("--agents", nargs="+", choices=sorted(AGENTS), default=sorted(AGENTS, reverse=True))
    parser.add_argument("--paths", nargs="+", choices=["eager", "compiled"], default=["eager", "compiled"])
    parser.add_argument("--budget", type=int, help="agent-episodes a cell plays (R × episodes); default: BUDGET")
    args = parser.parse_args()
    rows = []
    print("| agent | runs | episodes | path | agent-steps/s | wall s | compile s |")
    print("| --- | ---: | ---: | --- | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for agent in args.agents:
            for runs in args.runs:
                episodes = max(MIN_EPISODES, (args.budget or BUDGET[agent]) // runs)
                for path in args.paths:
                    if path == "compiled" and episodes < COMPILES_FROM[agent]:
                        continue  # the eager path again (module doc)
                    row = job(agent, runs, episodes, path == "compiled", Path(tmp) / f"{agent}_{runs}_{path}")
                    rows.append(row)
                    print(
                        f"| {agent} | {runs} | {episodes} | {row['path']} | {row['agent_steps_per_s']:.0f} "
                        f"| {row['wall_time_s']:.1f} | {row['compile_time_s']:.1f} |",
                        flush=True,
                    )
    save_results(ROOT / "benchmarks" / "results.json", "runs_scaling", "cpu", rows=rows)


if __name__ == "__main__":
    main()
