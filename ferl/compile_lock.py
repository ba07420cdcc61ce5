"""Inductor behind a lock per graph, so that processes that share a compile cache compile a graph once.

The jobs of a sweep share inductor's cache on disk (``ferl.compiled.cache_dir``). When two of them
reach the same graph at the same time (two jobs of one task side by side, a noise grid's levels),
both miss the cache and both compile it: tens of seconds of a core each, the second for nothing.
Here the backend that ``torch.compile`` hands each traced graph to takes an advisory lock named by
the graph (its code, its inputs' sizes and types, the compiler's options) before it asks inductor:
the second process waits, then finds the first one's graph in the cache and loads it. The lock
changes when a graph is compiled, never what is computed, so no result depends on timing.

Graphs that differ only in what the name leaves out (a constant held as a tensor attribute) share a
lock: the second waits, then compiles its own, as it would have. A file system without locks runs
without them (each process compiles, as before). ``fcntl.flock`` is dropped by the kernel when its
process ends, however it ends, so a killed compiler leaves no lock held; the lock files (a few
bytes each, in ``<cache>/ferl_graph_locks``) are never removed, as a removal could race a waiting process.
"""

import fcntl
import functools
import hashlib
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from pathlib import Path

import torch


def graph_name(gm: torch.fx.GraphModule, example_inputs: list, options: dict) -> str:
    """A hex name for a traced graph: its Python code, every input's size, stride, type and device,
    the compiler's options and torch's version. Sizes are read from the graph's own placeholders,
    where a size compiled generic is a symbol: ``example_inputs`` hold the values of the call that
    traced it (the floor's 294 clean pixels a step at one noise level, 196 at another), and a name
    made of them would give one graph a name per level, so that its compilers would not wait for
    each other."""
    traced = gm.graph.find_nodes(op="placeholder")
    if len(traced) == len(example_inputs):
        example_inputs = [node.meta.get("example_value", x) for node, x in zip(traced, example_inputs)]
    inputs = [
        (tuple(map(str, x.shape)), tuple(map(str, x.stride())), str(x.dtype), str(x.device))
        if isinstance(x, torch.Tensor)
        else repr(x)
        for x in example_inputs
    ]
    chosen = sorted((k, getattr(v, "__qualname__", repr(v))) for k, v in options.items())
    text = repr((gm.code, inputs, chosen, torch.__version__))
    return hashlib.sha256(text.encode()).hexdigest()[:32]


@contextmanager
def graph_lock(folder: Path, name: str) -> Iterator[None]:
    """Hold the lock ``folder/<name>.lock`` (waiting, with one line, while another process holds it);
    without it where the file system refuses locks."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"{name}.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError:
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(
                "ferl: another process is compiling the same graph; waiting to load it from the cache",
                file=sys.stderr,
            )
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            pass  # locks refused here: compile without
        yield
    finally:
        os.close(fd)  # drops the flock


def backward_inside() -> AbstractContextManager:
    """AOT autograd's switch that lowers a graph's backward with its forward, inside the lock (by
    default it lowers it at the backward's first call). A torch without the switch (2.8) lowers the
    backward outside the lock: two processes may then both compile it, and compute the same."""
    config = torch._functorch.config
    if hasattr(config, "force_non_lazy_backward_lowering"):
        return config.patch(force_non_lazy_backward_lowering=True)
    return nullcontext()


@functools.cache
def locked_inductor(options: tuple[tuple[str, object], ...], folder: str) -> Callable:
    """The ``torch.compile`` backend: inductor (``compile_fx``) with ``options``, behind the graph's
    lock in ``folder``. One object per options and folder, as dynamo reuses a compiled graph only
    for the backend that compiled it."""
    patches, locks = dict(options), Path(folder)

    def backend(gm: torch.fx.GraphModule, example_inputs: list):
        from torch._inductor.compile_fx import compile_fx

        with graph_lock(locks, graph_name(gm, example_inputs, patches)), backward_inside():
            return compile_fx(gm, example_inputs, config_patches=patches)

    return backend
