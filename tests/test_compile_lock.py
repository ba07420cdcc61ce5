"""Processes that share a compile cache compile a graph once (ferl/compile_lock.py): two processes
started together on an empty cache, each compiling the same function, miss inductor's cache once
between them; the other waits for the first and loads its graph. Without the lock both miss (each
compiles the graph: seen when the backend was plain inductor)."""

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import torch

from ferl.compile_lock import graph_lock, graph_name

ROOT = Path(__file__).resolve().parents[1]
COMPILE_ONE = """
import json, sys, torch
from torch._dynamo.utils import counters
from ferl.compiled import compiled

def steps(x, w):
    for _ in range(6):
        x = torch.tanh(x @ w) * 0.5 + x.sin()
    return x

out = compiled(steps, torch.device("cpu"), "a test graph")(torch.ones(4, 8), torch.eye(8))
print(json.dumps({"miss": counters["inductor"]["fxgraph_cache_miss"], "hit": counters["inductor"]["fxgraph_cache_hit"],
                  "sum": out.sum().item()}))
"""


def test_two_processes_compile_a_graph_once(tmp_path):
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", COMPILE_ONE], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    results = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-2000:] for _, err in results]
    counts = [json.loads(out.strip().splitlines()[-1]) for out, _ in results]
    assert sorted(c["miss"] for c in counts) == [0, 1]  # one compiled, the other loaded
    assert sum(c["hit"] for c in counts) == 1
    assert counts[0]["sum"] == counts[1]["sum"]
    assert sum("compiled a test graph" in err for _, err in results) == 1


def test_the_lock_waits_for_its_holder(tmp_path):
    """A second holder of the same name waits until the first lets go; another name does not."""
    order = []
    with graph_lock(tmp_path, "g"):
        waiter = threading.Thread(target=lambda: graph_lock_then(tmp_path, "g", order))
        other = threading.Thread(target=lambda: graph_lock_then(tmp_path, "h", order))
        waiter.start(), other.start()
        other.join(timeout=30)
        waiter.join(timeout=0.5)
        assert order == ["h"] and waiter.is_alive()
        order.append("released")
    waiter.join(timeout=30)
    assert order == ["h", "released", "g"]


def graph_lock_then(folder, name, order):
    with graph_lock(folder, name):
        order.append(name)


def traced_name(size: int, generic: bool) -> str:
    """The name ``graph_name`` gives the graph that dynamo traces for an input of ``size`` columns,
    compiled afresh (as in a new process), with that size generic or not."""
    names = []

    def backend(gm, example_inputs):
        names.append(graph_name(gm, example_inputs, {}))
        return gm.forward

    torch._dynamo.reset()
    x = torch.ones(3, size)
    if generic:
        torch._dynamo.maybe_mark_dynamic(x, 1)
    torch.compile(lambda x: (x * 2).sum(1), backend=backend, dynamic=None if generic else False)(x)
    torch._dynamo.reset()
    return names[0]


def test_a_graph_generic_in_a_size_has_one_name_whatever_size_traced_it():
    """Its compilers wait for each other when they trace it at different sizes (the floor's noise
    levels); graphs specialised to different sizes are different graphs, with different names."""
    assert traced_name(5, generic=True) == traced_name(7, generic=True)
    assert traced_name(5, generic=False) != traced_name(7, generic=False)
