"""What one call of a compiled graph costs before any arithmetic, against the same operations eagerly.

    python benchmarks/bench_call_overhead.py [--inputs 2 12 24] [--calls 2000]

The graph adds one (10, 20, 20) tensor to each of n others (``ferl.compiled.compiled``: inductor with
the fast path's CPU options, ``cpp_wrapper`` among them), so its arithmetic is a few µs and the rest
is the call: the guards, the wrapper, the outputs. One thread. Prints µs a call, compiled and eager;
docs/performance.md ("The candidates, side by side") uses it to say why the predictors'
pattern-mode SGD keeps graphs of whole SGD steps.
"""

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ferl.compiled import compiled


def add_to_each(weights: list, x: torch.Tensor) -> list:
    """x added to each of ``weights``."""
    return [w + x for w in weights]


def per_call(fn, args: tuple, calls: int) -> float:
    """µs a call of ``fn(*args)``, the mean of ``calls`` calls."""
    started = time.perf_counter()
    for _ in range(calls):
        fn(*args)
    return (time.perf_counter() - started) / calls * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, nargs="+", default=[2, 12, 24])
    parser.add_argument("--calls", type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    graph = compiled(add_to_each, torch.device("cpu"), "the probe")
    print("| tensors added to | compiled, µs a call | eager, µs a call |\n| ---: | ---: | ---: |")
    for n in args.inputs:
        inputs = ([torch.randn(10, 20, 20) for _ in range(n)], torch.randn(10, 20, 20))
        graph(*inputs)  # compiles, or loads from the cache
        print(f"| {n} | {per_call(graph, inputs, args.calls):.1f} | {per_call(add_to_each, inputs, args.calls):.1f} |")


if __name__ == "__main__":
    main()
