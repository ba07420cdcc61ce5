"""Analyze finished runs: figures, their numbers and a claims-vs-measurements report.

    python analyze.py RUN_OR_SWEEP_DIR [more dirs ...]

    python analyze.py SWEEP_DIR --readme README.md --readme docs/reproduction.md
        # also paste the results into these pages: the scorecard, the claims table

A directory holding `summary.json` is a run, any other a sweep of runs; what each gets is
described in `ferl/analysis/runner.py` and docs/records.md ("Analysis"): ferl's generic analysis,
with the dissertation's claims, figures and findings that `reproduction/` registers into it.
"""

import sys

try:  # Ctrl-C while the imports run: one line, not importlib's traceback
    import argparse
    from pathlib import Path

    import reproduction  # noqa: F401 — registers the dissertation's analyses (ferl.analysis.dispatch)
    from ferl.analysis import runner
except KeyboardInterrupt:
    print("analyze.py: interrupted by SIGINT while starting: nothing was written", file=sys.stderr)
    sys.exit(130)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=runner.PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "dirs",
        nargs="+",
        type=Path,
        metavar="RUN_OR_SWEEP_DIR",
        help="a run directory (holds summary.json) or a directory of runs",
    )
    parser.add_argument(
        "--readme",
        type=Path,
        action="append",
        default=[],
        metavar="PAGE.md",
        help="paste a sweep's results into this page's generated blocks (the "
        "claims table, the scorecard), between their marker lines; repeatable",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="analyse every run again, also those whose records and code are unchanged since "
        "their last analysis (which are otherwise kept)",
    )
    args = parser.parse_args(argv)
    return runner.main(args.dirs, args.readme, args.force)


if __name__ == "__main__":
    sys.exit(main())
