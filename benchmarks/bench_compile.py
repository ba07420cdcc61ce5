"""A graph's first compile against inductor's settings: one cold ``train.py`` job per cell.

    python benchmarks/bench_compile.py [--corridors 6 20] [--settings '{}' '{"realize_reads_threshold": 4}']

Each cell runs the recurrent Q-learner (GRU core, linear head) for 20 episodes of the passive
T-maze at corridor L (T_max = L + 1), in a subprocess with an empty ``TORCHINDUCTOR_CACHE_DIR``,
so that its episode graph and its replay step are compiled afresh; ``settings`` (JSON) update
``ferl.compiled.CPU_INDUCTOR_OPTIONS`` in that process (``{}``: ferl's own; ``{"realize_reads_threshold":
4}``: inductor's default, which ferl changed, docs/performance.md "Why an unrolled episode compiled
slowly"). The seconds are ``summary.json``'s ``compile_time_s`` (both graphs' first calls) and the
job's ``wall_time_s``. Prints a markdown table and merges it into benchmarks/results.json under
"compile_settings".
"""

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.jobs import PASSIVE_Q, train_summary  # noqa: E402
from benchmarks.report import save_results  # noqa: E402

AGENT = [*PASSIVE_Q, "trainer.n_episodes=20"]
# the child: ferl's options updated, then train.py as ``python train.py`` would run it
CHILD = (
    "import json, runpy, sys; import ferl.compiled as c; c.CPU_INDUCTOR_OPTIONS.update(json.loads(sys.argv[1])); "
    "sys.argv = ['train.py', *sys.argv[2:]]; runpy.run_path('train.py', run_name='__main__')"
)


def job(corridor: int, settings: str, out: Path) -> dict:
    """One cold job; its summary's compile and wall seconds."""
    command = [sys.executable, "-c", CHILD, settings, *AGENT, f"env.corridor_length={corridor}", f"hydra.run.dir={out}"]
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache}
        summary = train_summary(command, out, f"bench_compile.py: corridor {corridor} with {settings}", env)
    return {
        "corridor": corridor,
        "settings": json.loads(settings),
        "compile_time_s": summary.get("compile_time_s", 0.0),
        "wall_time_s": summary["wall_time_s"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--corridors", type=int, nargs="+", default=[6, 20])
    parser.add_argument("--settings", nargs="+", default=["{}", '{"realize_reads_threshold": 4}'])
    args = parser.parse_args()
    import torch._inductor.config as inductor_config

    for settings in args.settings:  # bad input: one line before any job
        try:
            unknown = [key for key in json.loads(settings) if not hasattr(inductor_config, key)]
        except json.JSONDecodeError as e:
            raise SystemExit(f"bench_compile.py: --settings {settings!r} is not JSON ({e})") from None
        if unknown:
            raise SystemExit(f"bench_compile.py: --settings {settings!r}: not an inductor option: {', '.join(unknown)}")
    rows = []
    print("| corridor L | T_max | settings | compile s | wall s |")
    print("| ---: | ---: | --- | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for corridor in args.corridors:
            for k, settings in enumerate(args.settings):
                row = job(corridor, settings, Path(tmp) / f"L{corridor}_{k}")
                rows.append(row)
                print(
                    f"| {corridor} | {corridor + 1} | `{settings}` | {row['compile_time_s']:.1f} | {row['wall_time_s']:.1f} |",
                    flush=True,
                )
    save_results(ROOT / "benchmarks" / "results.json", "compile_settings", "cpu", rows=rows)


if __name__ == "__main__":
    main()
