"""The fast path: a fused chunk of steps as one torch.compiled graph, its cache on disk, and eager.

Small networks spend their time in per-operation overhead, not arithmetic: a T-maze step is ~50
tensor operations of a few µs each on tensors of a few hundred numbers. A chunk — K online TD steps
of the floor (``ferl.trainers.chunks``), a whole T-maze episode (``ActorEpisodes.episode``),
K pattern-mode SGD steps (``ferl.predictors.training``) — is written as a plain loop over tensors
with its random numbers drawn beforehand, so ``torch.compile`` can trace it as one graph: inductor
fuses the element-wise work into generated loops, and on a CPU its kernels are called from C++
(``cpp_wrapper``), so Python runs once per chunk. The same function run eagerly is the reference.

Compiling takes tens of seconds; inductor keeps what it built in ``cache_dir()`` (by default
``~/.cache/ferl/inductor/<vector ISA>``; ``TORCHINDUCTOR_CACHE_DIR`` if set), so only a machine's
first run of a configuration pays, and that run says so in one line. Without a C++ compiler (CPU) or Triton
(CUDA) a run warns once and runs eagerly.
"""

import contextlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from ferl.compile_lock import locked_inductor
from ferl.messages import warn

CACHE_ENV = "TORCHINDUCTOR_CACHE_DIR"
DEFAULT_CACHE = Path.home() / ".cache" / "ferl" / "inductor"
_first_calls = [0.0]  # seconds this process has spent in compiled functions' first calls
# Steps one compiled graph plays (docs/performance.md, "Graphs of fixed size"; measured by
# benchmarks/bench_chunks.py on the 2-core CPU): such graphs are called ⌈T / K⌉ times with their
# state carried, so that compiling costs the same at every T_max. The recurrent Q-learner's replay
# BPTT runs chunks of CHUNK_STEPS steps of core and head (8: 4 ran ~35 % slower, 16 compiled
# longer). An actor phase's episode runs chunks of at most EPISODE_CHUNK_STEPS steps of environment,
# memories and actor, whose compile time grows by seconds a step (4: as fast a step as 8 or 16,
# its graph compiled in about half 8's time; 1 or 2: 0.5–0.75 × the speed).
CHUNK_STEPS = 8
EPISODE_CHUNK_STEPS = 4
# Steps one compiled graph of whole SGD steps of the predictors' BPTT may unroll (sequences of at
# most ``ferl.predictors.training.TIME_CHUNKED_FROM`` steps; longer ones train in chunks of time
# steps). Inductor's compile time grows faster than the graph: the recurrent Q-learner's unrolled
# episode and replay graphs took ~95 s at T_max = 44 on the 2-core CPU and were still compiling
# after 24 min at T_max = 101 (docs/performance.md). 80 keeps the dissertation's chunks (8 SGD
# steps of ≤ 10 actions); longer sequences take fewer steps a graph (``unroll_chunk``).
MAX_UNROLLED_STEPS = 80
# Inductor's options on a CPU. ``cpp_wrapper``: the kernels are called from C++. Inductor inlines a
# pointwise value into each of its readers until it has more than ``realize_reads_threshold``
# (default 4) readers. An unrolled episode carries small per-run recurrences (the time step, done,
# the cell) whose every step reads the step before, so inlined values nest step on step and writing
# the kernels (its Scheduler.codegen) outgrows the unroll: the recurrent Q-learner's passive-maze
# episode and replay step at T_max = 21 took 473 s to compile. Storing every value read more than
# once compiles them in 83 s and runs them as fast; the matching maze's graphs compile and run as before (docs/performance.md,
# "Why an unrolled episode compiled slowly").
CPU_INDUCTOR_OPTIONS: dict[str, str | int | bool | Callable] = {"cpp_wrapper": True, "realize_reads_threshold": 1}


def compile_seconds() -> float:
    """Seconds this process has spent in the first calls of compiled functions: compiling them, or
    tracing them and loading what the cache holds (summary.json ``compile_time_s``; a phase's
    agent-steps/s leaves them out)."""
    return _first_calls[0]


def run_clock() -> float:
    """A clock (seconds) that stands still during compiled functions' first calls: what a phase's
    agent-steps/s is timed with, so that it measures running, not compiling."""
    return time.perf_counter() - _first_calls[0]


def cache_dir() -> Path:
    """Where inductor keeps compiled graphs across runs (set before the first compile): by default a
    folder per vector ISA (``vector_isa``). Inductor's cache key leaves the ISA out: a home folder
    shared by an AVX2 and an AVX-512 machine (a cluster's nodes), or a run with
    ``ATEN_CPU_CAPABILITY=avx2`` before one without, made the second load the other's graphs, and
    it ended in "double free or corruption" (seen here with torch 2.13, docs/reliability.md)."""
    if CACHE_ENV not in os.environ:
        os.environ[CACHE_ENV] = str(DEFAULT_CACHE / vector_isa())
    return Path(os.environ[CACHE_ENV])


def remember_isa_probes() -> None:
    """Inductor accepts a vector ISA once a small library built with its flags (kept in inductor's
    cache) loads in a fresh Python process: ten such processes, about 1.8 s, in every process that
    compiles a graph or loads one (docs/performance.md, "The vector ISA probes, once per
    machine"). A library that loaded once loads again: a success is remembered in a file beside the
    library (``<library>.loads``), which later processes read instead. A failure is not remembered,
    so it is probed again, as before. Installed by ``vector_isa`` and ``compiled``, before the first
    probe, once; where inductor probes differently (another torch), nothing changes."""
    from torch._inductor.cpu_vec_isa import VecISA

    probe = getattr(VecISA, "_probe_load", None)
    if probe is None or getattr(probe, "remembered", False):
        return

    def remembered(isa, library: str) -> bool:
        mark = Path(library + ".loads")
        if mark.exists():
            return True
        loads = probe(isa, library)
        if loads:
            with contextlib.suppress(OSError):  # a read-only cache: probe again next time
                mark.touch()
        return loads

    remembered.remembered = True  # type: ignore[attr-defined]
    setattr(VecISA, "_probe_load", remembered)  # noqa: B010 — a private hook of inductor's, replaced on purpose


def vector_isa() -> str:
    """The CPU vector instructions inductor generates code for here, e.g. ``avx2`` or
    ``avx512_avx512_vnni_amx_tile`` (it follows ``ATEN_CPU_CAPABILITY``); ``none`` without."""
    from torch._inductor.cpu_vec_isa import pick_vec_isa

    remember_isa_probes()
    isa = pick_vec_isa()
    return "_".join(str(isa).split()) if isa else "none"


def compiler_missing(device: torch.device) -> str | None:
    """Why graphs cannot be compiled for ``device`` here, or None."""
    if device.type == "cuda":
        from torch.utils._triton import has_triton

        return None if has_triton() else "Triton is not installed"
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler

        get_cpp_compiler()
    except Exception as e:  # noqa: BLE001 — whatever inductor's search raises, the reason is its message
        return f"no C++ compiler ({str(e).splitlines()[0] if str(e) else type(e).__name__})"
    return None


def fast_path(wanted: bool, device: torch.device) -> bool:
    """Whether to compile: ``compile=true`` (the default) where a compiler exists; else one
    warning and the eager path, which computes the same steps."""
    if not wanted:
        return False
    cache_dir()  # before anything of inductor's sets its own default
    reason = compiler_missing(device)
    if reason is not None:
        warn(f"compile=true: {reason}; running eagerly (slower, the same steps; compile=false silences this)")
        return False
    return True


def unroll_chunk(steps_each: int, wanted: int) -> int:
    """How many of ``wanted`` steps of ``steps_each`` unrolled steps one graph takes: as many as
    fit in MAX_UNROLLED_STEPS, at least one."""
    return max(1, min(wanted, MAX_UNROLLED_STEPS // max(steps_each, 1)))


def chunk_count(steps: int, chunk: int | None = None) -> int:
    """How many graphs of ``chunk`` (by default ``CHUNK_STEPS``) steps play ``steps`` steps (the
    last one padded)."""
    return -(-steps // (chunk or CHUNK_STEPS))


def in_chunks(run_chunk: Callable, x: torch.Tensor, state, chunk: int | None = None):
    """Outputs of every step of x (R, B, N, …) along dim 2 (a tensor, or a tuple of them),
    computed ``chunk`` (by default ``CHUNK_STEPS``) steps at a time by ``run_chunk(x_chunk, state)
    -> (out, state)``, out (R, B, chunk, …) or a tuple of such, from ``state``: the graph that
    ``run_chunk`` compiles is the same for every N (the last chunk padded with zero inputs, whose
    outputs are dropped; a recurrence runs forward, so they reach no earlier step). Each chunk is
    a fresh contiguous tensor, so that its storage offset is 0 in every call. Under autograd the
    chunks' compiled backwards chain through the carried state (BPTT over the whole sequence)."""
    steps, chunk = x.shape[2], chunk or CHUNK_STEPS
    pad = chunk_count(steps, chunk) * chunk - steps
    if pad:
        x = torch.cat([x, x.new_zeros(*x.shape[:2], pad, *x.shape[3:])], 2)
    outs = []
    for t in range(0, steps + pad, chunk):
        out, state = run_chunk(x[:, :, t : t + chunk].contiguous(), state)
        outs.append(out)
    if isinstance(outs[0], tuple):  # several outputs a step
        return tuple(torch.cat(parts, 2)[:, :, :steps] for parts in zip(*outs))
    return torch.cat(outs, 2)[:, :, :steps]


def first_call_compiles(fn: Callable) -> Callable:
    """``fn``, its first call counted whole as compiling time (``compile_seconds``): for a function
    that runs compiled graphs under autograd, whose backward graphs are compiled by their first
    backward call, outside ``compiled``'s timing of their forward."""
    first = True

    def call(*args):
        nonlocal first
        if not first:
            return fn(*args)
        first = False
        before, started = _first_calls[0], time.perf_counter()
        out = fn(*args)
        _first_calls[0] = before + time.perf_counter() - started  # the graphs' own first calls are in it
        return out

    return call


def size_generic(x: torch.Tensor, first_dim: int, end_dim: int | None = None) -> torch.Tensor:
    """A copy of ``x`` whose sizes ``first_dim`` … ``end_dim`` − 1 (to the last where None) a
    compiled graph takes as symbols, not constants: one graph then serves every size a
    configuration gives them. A copy, because a graph generic in sizes is also generic in storage
    offsets, and a view's offset differs from call to call; sizes 0 and 1 stay specialised
    (dynamo's rule). ``x`` itself where it has no such size (no copy)."""
    if x.dim() <= first_dim:
        return x
    x = x.clone()
    for dim in range(first_dim, x.dim() if end_dim is None else end_dim):
        torch._dynamo.maybe_mark_dynamic(x, dim)
    return x


def compiled(fn, device: torch.device, what: str, generic: Callable[[tuple], tuple] | None = None):
    """``fn`` as one graph per input shape (fullgraph: a graph break would silently bring back the
    per-operation overhead), its kernels called from C++ on a CPU. The first call that had to
    compile rather than load from the cache prints one line saying so, with its time. Where fn
    cannot be compiled (an operation dynamo cannot trace, say, in a user's actor) it warns once
    and runs eagerly: compiling fails before the graph runs, so nothing has changed yet.

    ``generic`` maps a call's arguments to the same arguments with some sizes marked generic
    (``size_generic``): the graph is compiled for any value of those and for the given values of
    every other size (no automatic dynamic shapes), so configurations that differ only in them
    share one graph, compiled once (the floor's noise levels: docs/performance.md)."""
    options = tuple(sorted(CPU_INDUCTOR_OPTIONS.items())) if device.type == "cpu" else ()
    backend = locked_inductor(options, str(cache_dir() / "ferl_graph_locks"))  # one compiler of a graph at a time
    remember_isa_probes()  # after cache_dir: importing inductor sets a cache folder of its own
    graph = torch.compile(fn, fullgraph=True, dynamic=None if generic else False, backend=backend)
    if generic is not None:
        static = torch._dynamo.config.patch(automatic_dynamic_shapes=False)
        graph = static(graph)
    first = True
    from torch._dynamo.exc import TorchDynamoException  # once here, not on every call
    from torch._dynamo.utils import counters

    def call(*args):
        nonlocal first, graph
        # a call that traced a new graph (the first, or new shapes) is compiling time, not running
        graphs, misses = counters["stats"]["unique_graphs"], counters["inductor"]["fxgraph_cache_miss"]
        started = time.perf_counter()
        if generic is not None and graph is not fn:  # after a failed trace: eager, no marks
            args = generic(args)
        try:
            out = graph(*args)
        except TorchDynamoException as e:
            if not first:
                raise
            warn(f"compile=true: {what} cannot be compiled ({str(e).splitlines()[0]}); running it eagerly")
            graph = fn
            return fn(*args)
        if first or counters["stats"]["unique_graphs"] > graphs:
            seconds = time.perf_counter() - started
            _first_calls[0] += seconds
            if counters["inductor"]["fxgraph_cache_miss"] > misses:
                print(
                    f"ferl: compiled {what} in {seconds:.0f} s (the first run of this configuration on this "
                    f"machine; later runs load it from {cache_dir()})",
                    file=sys.stderr,
                )
        first = False
        return out

    return call
