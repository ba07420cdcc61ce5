"""Ways to compile BPTT through a long episode, side by side: each candidate in its own process.

    python benchmarks/bench_bptt_candidates.py [--steps 64 256] [--candidates eager chunk4 chunk8 chunk16 scan]

The work is the recurrent Q-learner's replay loss with its gradient: a GRU core and linear head
(``ferl.actors.recurrent_cores.GRUCore``, ``ferl.actors.q_heads.LinearHead``) over N steps of
10 runs × 16 episodes (H = 20, 6 observation values + 4 actions in), loss Σ Q², its gradient by
``torch.autograd.grad``. Candidates:

* ``eager``: the loop over time, no compiling (the reference of every gradient);
* ``chunkK``: a compiled graph of K steps called ⌈N / K⌉ times, the state carried, autograd
  chaining the chunks' compiled backward graphs (``ferl.compiled.in_chunks``, what ferl does);
* ``scan``: the whole loop as ``torch._higher_order_ops.scan`` in one compiled graph (its body one
  step), inductor without ``cpp_wrapper`` (with it the generated C++ did not compile here).

Every process first compiles a trivial graph, so that inductor's one-time set-up of an empty cache
(~16 s here) is not charged to the first candidate: "compile s" is the candidate's first call
(forward and backward graphs). "ms" is one loss and gradient afterwards, the mean of 10. The
gradient's largest relative difference from eager is beside it. Merges the rows into
benchmarks/results.json under "bptt_candidates".
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import save_results  # noqa: E402

R, B, S, A, H = 10, 16, 6, 4, 20


def candidate(name: str, steps: int) -> dict:
    """Run in the child: one candidate's first call and its steady time."""
    import torch

    from ferl.actors.q_heads import LinearHead
    from ferl.actors.recurrent_cores import GRUCore
    from ferl.compiled import CPU_INDUCTOR_OPTIONS, in_chunks

    core, head = GRUCore(S + A, H), LinearHead(H, A)
    g = torch.Generator().manual_seed(0)
    params = {n: torch.randn(R, *shape, generator=g) * 0.2 for n, shape in {**core.shapes(), **head.shapes()}.items()}
    x = torch.randn(R, B, steps, S + A, generator=g)
    readout = lambda p: lambda h: head.q(p, h)  # noqa: E731

    def compile_(fn, **options):
        return torch.compile(fn, fullgraph=True, dynamic=False, options={**CPU_INDUCTOR_OPTIONS, **options})

    warm = compile_(lambda a, b: (a * b).sin() + b)
    warm(torch.randn(3, requires_grad=True), torch.randn(3)).sum().backward()

    def eager(p):
        return core.unroll(p, x, readout(p))

    if name == "eager":
        q_of = eager
    elif name.startswith("chunk"):
        chunk = compile_(lambda p, xc, state: core.run(p, xc, state, readout(p)))
        k = int(name.removeprefix("chunk"))
        zero = core.zero_state(x)

        def q_of(p):
            return in_chunks(lambda xc, state: chunk(p, xc, state), x, zero.clone().requires_grad_(), k)
    elif name == "scan":
        from torch._higher_order_ops.scan import scan

        def scanned(p, xs):  # xs (N, R, B, X)
            def body(state, xt):
                state = core.step(p, xt, state)
                return state, head.q(p, core.hidden(state))

            return scan(body, xs.new_zeros(R, B, H), xs)[1].permute(1, 2, 0, 3)

        graph = compile_(scanned, cpp_wrapper=False)
        xs = x.permute(2, 0, 1, 3).contiguous()

        def q_of(p):
            return graph(p, xs)
    else:
        raise SystemExit(f"bench_bptt_candidates.py: no candidate {name!r}")

    def gradient(fn):
        p = {n: v.clone().requires_grad_() for n, v in params.items()}
        return torch.autograd.grad(fn(p).square().sum(), list(p.values()))

    started = time.perf_counter()
    grads = gradient(q_of)
    first = time.perf_counter() - started
    reference = gradient(eager)
    difference = max(float((a - b).abs().max() / b.abs().max()) for a, b in zip(grads, reference))
    started = time.perf_counter()
    for _ in range(10):
        gradient(q_of)
    return {
        "candidate": name,
        "steps": steps,
        "compile_s": 0.0 if name == "eager" else first,
        "ms": (time.perf_counter() - started) / 10 * 1e3,
        "relative_difference": difference,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--candidates", nargs="+", default=["eager", "chunk4", "chunk8", "chunk16", "scan"])
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(candidate(args.child[0], int(args.child[1]))))
        return
    rows = []
    print("| candidate | N | compile s | ms (loss and gradient) | max relative difference from eager |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for steps in args.steps:
        for name in args.candidates:
            with tempfile.TemporaryDirectory() as cache:
                done = subprocess.run(
                    [sys.executable, __file__, "--child", name, str(steps)],
                    capture_output=True,
                    text=True,
                    env={**os.environ, "TORCHINDUCTOR_CACHE_DIR": cache},
                )
            if done.returncode != 0:
                tail = done.stderr.strip().splitlines()[-1:] or ["no output"]
                row = {"candidate": name, "steps": steps, "failed": tail[0][:200]}
                print(f"| {name} | {steps} | failed: {row['failed']} | | |", flush=True)
            else:
                row = json.loads(done.stdout.strip().splitlines()[-1])
                print(
                    f"| {name} | {steps} | {row['compile_s']:.1f} | {row['ms']:.1f} | {row['relative_difference']:.1e} |",
                    flush=True,
                )
            rows.append(row)
    save_results(ROOT / "benchmarks" / "results.json", "bptt_candidates", "cpu", rows=rows)


if __name__ == "__main__":
    main()
