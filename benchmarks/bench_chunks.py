"""Graphs of a fixed number of steps against the horizon: one ``train.py`` job per cell.

    python benchmarks/bench_chunks.py [--corridors 10 50 200 1000] [--episodes 1000] [--modes eager cold warm]
                                      [--chunks 4] [--agent recurrent_q]

Each cell runs the recurrent Q-learner (GRU core, linear head; ``--agent ferl``: the dissertation's
FERL actor on the online trainer's LSTM predictor) on the passive T-maze at corridor L
(T_max = L + 1), 10 runs, in a subprocess:

* ``eager``: ``compile=false``;
* ``cold``: ``compile=true`` with an empty ``TORCHINDUCTOR_CACHE_DIR`` (every graph compiled);
* ``warm``: the same again on the cache the cold job filled.

``--chunks`` sets ``ferl.compiled.EPISODE_CHUNK_STEPS`` in the job's process (the most steps one
episode graph plays; the replay's chunks stay ``CHUNK_STEPS``).
Prints a markdown table: the whole process's seconds (started to ended, Python's start and
imports included), the job's ``wall_time_s`` and ``compile_time_s``, agent-steps/s (running, not
compiling), the solved runs, and each graph's first compile as the job printed it ("ferl: compiled
… in N s"). Merges the rows into benchmarks/results.json under "fixed_size_graphs".
"""

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import PASSIVE_Q, train_summary  # noqa: E402
from benchmarks.report import save_results  # noqa: E402

AGENTS = {
    "recurrent_q": PASSIVE_Q,
    "ferl": ["experiment=passive_tmaze", "predictor.joint.memory=lstm"],
}
# the child: EPISODE_CHUNK_STEPS set, then train.py as ``python train.py`` would run it
CHILD = (
    "import runpy, sys; import ferl.compiled as c; c.EPISODE_CHUNK_STEPS = int(sys.argv[1]); "
    "sys.argv = ['train.py', *sys.argv[2:]]; runpy.run_path('train.py', run_name='__main__')"
)
COMPILED_LINE = re.compile(r"ferl: compiled (.+) in (\d+) s")


def job(agent: str, corridor: int, episodes: int, mode: str, chunk: int, out: Path, cache: Path) -> dict:
    """One job in a subprocess; its summary's numbers, the process's seconds and the compile lines."""
    overrides = [*AGENTS[agent], f"env.corridor_length={corridor}", f"trainer.n_episodes={episodes}"]
    overrides += [f"compile={mode != 'eager'}", f"hydra.run.dir={out}"]
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache)}
    command, stderr = [sys.executable, "-c", CHILD, str(chunk), *overrides], []
    started = time.perf_counter()
    summary = train_summary(command, out, f"bench_chunks.py: {agent} L={corridor} {mode}", env, stderr)
    process_s = time.perf_counter() - started
    return {
        "agent": agent,
        "corridor": corridor,
        "t_max": corridor + 1,
        "episodes": episodes,
        "mode": mode,
        "chunk_steps": chunk,
        "process_s": process_s,
        "wall_time_s": summary["wall_time_s"],
        "compile_time_s": summary.get("compile_time_s", 0.0),
        "agent_steps_per_s": summary["agent_steps_per_s"],
        "solved": int(sum(summary["metrics"].get("solved", []))),
        "graphs": [(what, int(s)) for what, s in COMPILED_LINE.findall(stderr[0])],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agent", choices=sorted(AGENTS), default="recurrent_q")
    parser.add_argument("--corridors", type=int, nargs="+", default=[10, 50, 200, 1000])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--modes", nargs="+", choices=["eager", "cold", "warm"], default=["eager", "cold", "warm"])
    parser.add_argument("--chunks", type=int, nargs="+", default=[4])
    args = parser.parse_args()
    if "warm" in args.modes and "cold" not in args.modes:
        raise SystemExit("bench_chunks.py: --modes warm needs cold before it (the cache it fills)")
    rows = []
    print(
        "| agent | L | T_max | episodes | mode | K | process s | wall s | compile s | agent-steps/s | solved | graphs (s) |"
    )
    print("| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for corridor in args.corridors:
            for chunk in args.chunks:
                cache = Path(tmp) / f"cache_L{corridor}_K{chunk}"  # empty for the cold job
                for mode in args.modes:
                    if mode == "eager" and chunk != args.chunks[0]:
                        continue  # eager has no chunks
                    out = Path(tmp) / f"L{corridor}_K{chunk}_{mode}"
                    row = job(args.agent, corridor, args.episodes, mode, chunk, out, cache)
                    rows.append(row)
                    graphs = "; ".join(f"{what}: {s}" for what, s in row["graphs"]) or "—"
                    print(
                        f"| {args.agent} | {corridor} | {corridor + 1} | {args.episodes} | {mode} | {chunk} | "
                        f"{row['process_s']:.1f} | {row['wall_time_s']:.1f} | {row['compile_time_s']:.1f} | "
                        f"{row['agent_steps_per_s']:.0f} | {row['solved']} | {graphs} |",
                        flush=True,
                    )
    save_results(ROOT / "benchmarks" / "results.json", f"fixed_size_graphs_{args.agent}", "cpu", rows=rows)


if __name__ == "__main__":
    main()
