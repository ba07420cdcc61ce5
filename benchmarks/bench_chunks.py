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
episode graph plays; the replay's chunks stay ``CHUNK_STEPS``). For ``--agent ferl`` (the online
trainer), ``--online-from N`` sets the episode counts from which its episodes and its replay
compile (``EPISODES_FUSED_FROM``, ``REPLAY_FUSED_FROM``), and ``--time-chunked-from N`` the length
from which the predictors' BPTT runs in chunks of time steps (``TIME_CHUNKED_FROM``; a large N: the
graphs of whole SGD steps, every step unrolled); the table then also splits the job's time into the
replay's and the acting's (``records/online.npz``).
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import PASSIVE_Q, train_summary  # noqa: E402
from benchmarks.report import save_results  # noqa: E402

AGENTS = {
    "recurrent_q": PASSIVE_Q,
    "ferl": ["experiment=passive_tmaze", "predictor.joint.memory=lstm"],
}
# the child: EPISODE_CHUNK_STEPS and the online trainer's thresholds set (an empty argument: the
# default), then train.py as ``python train.py`` would run it
CHILD = """
import runpy, sys
import ferl.compiled as c, ferl.predictors.training as t, ferl.trainers.online_episodes as o
c.EPISODE_CHUNK_STEPS = int(sys.argv[1])
if sys.argv[2]:
    o.EPISODES_FUSED_FROM = o.REPLAY_FUSED_FROM = int(sys.argv[2])
if sys.argv[3]:
    t.TIME_CHUNKED_FROM = int(sys.argv[3])
sys.argv = ["train.py", *sys.argv[4:]]
runpy.run_path("train.py", run_name="__main__")
"""
COMPILED_LINE = re.compile(r"ferl: compiled (.+) in (\d+) s")


def job(
    agent: str, corridor: int, episodes: int, mode: str, chunk: int, out: Path, cache: Path, online=("", "")
) -> dict:
    """One job in a subprocess; its summary's numbers, the process's seconds and the compile lines;
    ``online``: ``--online-from`` and ``--time-chunked-from`` as strings ("": the default)."""
    overrides = [*AGENTS[agent], f"env.corridor_length={corridor}", f"trainer.n_episodes={episodes}"]
    overrides += [f"compile={mode != 'eager'}", f"hydra.run.dir={out}"]
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache)}
    command, stderr = [sys.executable, "-c", CHILD, str(chunk), *online, *overrides], []
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
        **split_of(out),
    }


def split_of(out: Path) -> dict:
    """The online trainer's seconds of replay and of acting (``records/online.npz``), if it ran."""
    path = out / "records" / "online.npz"
    if not path.exists():
        return {}
    with np.load(path) as online:
        return {"replay_s": float(online["predictor_time_s"]), "acting_s": float(online["actor_time_s"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agent", choices=sorted(AGENTS), default="recurrent_q")
    parser.add_argument("--corridors", type=int, nargs="+", default=[10, 50, 200, 1000])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--modes", nargs="+", choices=["eager", "cold", "warm"], default=["eager", "cold", "warm"])
    parser.add_argument("--chunks", type=int, nargs="+", default=[4])
    parser.add_argument("--online-from", default="", help="EPISODES_FUSED_FROM and REPLAY_FUSED_FROM (--agent ferl)")
    parser.add_argument("--time-chunked-from", default="", help="TIME_CHUNKED_FROM (the predictors' BPTT)")
    args = parser.parse_args()
    if "warm" in args.modes and "cold" not in args.modes:
        raise SystemExit("bench_chunks.py: --modes warm needs cold before it (the cache it fills)")
    rows = []
    print(
        "| agent | L | T_max | episodes | mode | K | process s | wall s | compile s | replay s | acting s "
        "| agent-steps/s | solved | graphs (s) |"
    )
    print("| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for corridor in args.corridors:
            for chunk in args.chunks:
                cache = Path(tmp) / f"cache_L{corridor}_K{chunk}"  # empty for the cold job
                for mode in args.modes:
                    if mode == "eager" and chunk != args.chunks[0]:
                        continue  # eager has no chunks
                    out = Path(tmp) / f"L{corridor}_K{chunk}_{mode}"
                    online = (args.online_from, args.time_chunked_from)
                    row = job(args.agent, corridor, args.episodes, mode, chunk, out, cache, online)
                    rows.append(row)
                    graphs = "; ".join(f"{what}: {s}" for what, s in row["graphs"]) or "—"
                    print(
                        f"| {args.agent} | {corridor} | {corridor + 1} | {args.episodes} | {mode} | {chunk} | "
                        f"{row['process_s']:.1f} | {row['wall_time_s']:.1f} | {row['compile_time_s']:.1f} | "
                        f"{row.get('replay_s', float('nan')):.1f} | {row.get('acting_s', float('nan')):.1f} | "
                        f"{row['agent_steps_per_s']:.0f} | {row['solved']} | {graphs} |",
                        flush=True,
                    )
    save_results(ROOT / "benchmarks" / "results.json", f"fixed_size_graphs_{args.agent}", "cpu", rows=rows)


if __name__ == "__main__":
    main()
