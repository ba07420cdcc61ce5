"""A measurement, not a ferl path: a run that compiles its graphs in the background and runs the
same steps eagerly until each graph is ready (docs/performance.md, "Compiling in the background").

    python -m benchmarks.background_compile experiment=table4_1_matching hydra.run.dir=DIR

runs ``train.py`` with these overrides, with inductor's own out-of-process compile
(``TORCHINDUCTOR_FX_COMPILE_MODE=async+subprocess``) patched where torch 2.13 cannot use it:

* its placeholder until the compile is ready compiles the graph in process too; here it runs the
  traced graph's operations eagerly;
* a graph with ``prims.iota`` (``torch.arange``) is refused by its pickler; here prims are sent;
* it cannot save an asynchronous result in the FX graph cache; here the compiled graph is saved
  when it arrives, so a later run loads it as after an ordinary compile.

Dynamo and AOT autograd still trace in the run's own thread (the first call); lowering, the C++
and g++ run in a child process on the other core. The calls before the switch run eagerly, so the
step at which a run switches depends on timing: what this prints, as seconds from the start. This
reaches into torch's private modules; it is kept to repeat the measurement, not to be imported.
"""

import atexit
import os
import pickle
import runpy
import sys
import time
from copy import copy

os.environ.setdefault("TORCHINDUCTOR_FX_COMPILE_MODE", "async+subprocess")

import torch._inductor.compile_fx as compile_fx  # after the mode is set: compile_fx reads it on import
import torch.fx._graph_pickler as graph_pickler
from torch._inductor import compile_fx_async as fx_async
from torch._inductor.codecache import FxGraphCache
from torch._inductor.output_code import OutputCode

STARTED = time.perf_counter()
switched: list[float] = []  # seconds from the start at which each graph's compiled code took over
_deferred: dict[int, tuple] = {}  # an asynchronous graph → its cache key, guards, local cache
_save_graph = FxGraphCache._save_graph
_pickle_op = graph_pickler._OpPickleData._pickle_op
_switch_to_compiled_fn = fx_async._AsyncOutputCode._switch_to_compiled_fn


class EagerGraph(OutputCode):
    """The traced graph's operations run one by one: what a call does before its compile is ready."""

    def __init__(self, gm):
        self.gm = gm
        self._boxed_call = True

    def __call__(self, inputs):
        return self.gm(*inputs)

    def post_compile(self, example_inputs, constants, graph_kwargs):
        pass

    def set_triton_bundle(self, triton_bundle):
        pass


def codegen_and_compile(self, gm, example_inputs, inputs_to_check, graph_kwargs):
    """``_AsyncFxCompile.codegen_and_compile`` with an eager placeholder instead of an in-process compile."""
    serialized = self._compile.serialize_compile(gm, example_inputs, inputs_to_check, graph_kwargs)
    if not serialized:
        return compile_fx._InProcessFxCompile().codegen_and_compile(gm, example_inputs, inputs_to_check, graph_kwargs)
    inputs, constants = serialized
    fx_async._AsyncFxCompile._stat_bg_started += 1
    future = self._compile._send_to_child_async(inputs)

    def arrived(pickled_output):
        output = pickled_output.deserialize(constants)
        self._compile._postprocess(output)
        return output.graph

    return fx_async._AsyncOutputCode(EagerGraph(gm), future, arrived)


def save_graph(key, compiled_graph, example_inputs, local, remote_cache):
    """The FX graph cache's save; an asynchronous graph is saved when its compiled code arrives,
    with the guards computed now, while the trace's shape environment exists."""
    if not isinstance(compiled_graph, fx_async._AsyncOutputCode):
        return _save_graph(key, compiled_graph, example_inputs, local, remote_cache)
    shape_env = FxGraphCache._get_shape_env()
    symints = FxGraphCache._filter_backed_symints(example_inputs)
    guards = shape_env.produce_guards_expression(placeholders=symints, guards=shape_env.get_pruned_guards(symints))
    _deferred[id(compiled_graph)] = (key, guards, local)
    return None


def switch_to_compiled_fn(self, args):
    out = _switch_to_compiled_fn(self, args)
    switched.append(round(time.perf_counter() - STARTED, 1))
    key, guards, local = _deferred.pop(id(self))
    graph = self._output_code
    graph.guards_expr = guards
    on_disk = copy(graph)
    on_disk.prepare_for_serialization()
    if local:
        FxGraphCache._write_to_local_cache(key, pickle.dumps(on_disk))
    return out


def pickle_op(name, datacls, options):
    """Prims (``prims.iota``) are torch's own operations: safe to unpickle wherever torch is."""
    return datacls(name) if name.startswith("torch.ops.prims.") else _pickle_op(name, datacls, options)


def report() -> None:
    print(
        f"background compile: {fx_async._AsyncFxCompile._stat_bg_started} graphs sent, "
        f"{fx_async._AsyncFxCompile._stat_eager_runs} eager and {fx_async._AsyncFxCompile._stat_compiled_runs} "
        f"compiled calls; switched at {switched} s",
        file=sys.stderr,
    )


fx_async._AsyncFxCompile.codegen_and_compile = codegen_and_compile
fx_async._AsyncOutputCode.set_triton_bundle = lambda self, triton_bundle: None
fx_async._AsyncOutputCode._switch_to_compiled_fn = switch_to_compiled_fn
FxGraphCache._save_graph = staticmethod(save_graph)
graph_pickler._OpPickleData._pickle_op = staticmethod(pickle_op)

if __name__ == "__main__":
    atexit.register(report)
    sys.argv = ["train.py", *sys.argv[1:]]
    runpy.run_path("train.py", run_name="__main__")
