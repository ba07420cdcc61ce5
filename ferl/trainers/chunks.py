"""Online TD steps in chunks: a chunk of K steps of every run is one call, optionally one compiled graph.

A chunk runs on random numbers drawn beforehand (action uniforms, a whole Gibbs chain's for Gibbs
selection; the environment's ``step_inputs``), so with ``compile=true`` it is one
``torch.compile``d graph: Python and per-operation overhead is paid once per chunk, not per step, and on a CPU the chunk runs for one
group of runs after another (``td_steps_by_groups``). With prefetching the random numbers of the
next chunks are drawn on a second thread while a chunk runs: the same draws from the same
generator in the same order, so the results do not change.
"""

import inspect
import math
import sys
from concurrent.futures import Future
from contextlib import contextmanager
from typing import NamedTuple

import torch

from ferl.actors.td import td_step
from ferl.compiled import compiled, size_generic

MAX_CHUNK = 16  # steps per call of td_steps (a divisor of the logging and checkpoint intervals)


class TDChunk(NamedTuple):
    """What a chunk of K TD steps hands back (a NamedTuple, so it traces under torch.compile): the
    state, action, its free energy and cache after the chunk, and every step's rewards and TD errors."""

    s: torch.Tensor  # (R, 1, S)
    a: torch.Tensor  # (R, 1)
    F_sa: torch.Tensor  # (R, 1)
    x_sa: torch.Tensor  # (R, 1, ·)
    rewards: torch.Tensor  # (K, R)
    deltas: torch.Tensor  # (K, R)


RUN_AXIS = {"s": 0, "a": 0, "F_sa": 0, "x_sa": 0, "rewards": 1, "deltas": 1}  # where each TDChunk field holds the runs


def td_steps(actor, env, generator, s, a, F_sa, x_sa, alive, lrs, betas, uniforms, *inputs):
    """len(lrs) online TD steps of every run (``td_step``, §3.2); step k uses α = lrs[k],
    β = betas[k], the action uniforms of step k and the environment's random inputs of index k
    (``env.step_inputs``). uniforms (K, R, 1, ``actor.uniforms_per_action``): one number for a
    softmax choice, a whole Gibbs chain's for Gibbs selection, which so runs inside the chunk too.

    s (R, 1, S), a (R, 1), F_sa (R, 1), x_sa (R, 1, ·): the state, action, its free energy and
    cache before the chunk; returns them after it, with rewards and TD errors (K, R): a ``TDChunk``.
    Runs with ``alive`` False (R, 1) keep their parameters (the divergence guard).
    """
    rewards, deltas = [], []
    for k in range(lrs.shape[0]):
        obs, r = env.step_with(a.squeeze(1), *(x[k] for x in inputs))
        s_next = obs.unsqueeze(1)
        a, F_sa, x_sa, delta = td_step(
            actor, s, a, F_sa, x_sa, r, s_next, lrs[k], betas[k], generator, uniforms[k], alive
        )
        rewards.append(r)
        deltas.append(delta.squeeze(1))
        s = s_next
    return TDChunk(s, a, F_sa, x_sa, torch.stack(rewards), torch.stack(deltas))


TD_STEPS_FIXED = len(inspect.signature(td_steps).parameters) - 1  # td_steps' arguments before *inputs


def td_steps_by_groups(steps, groups: list[slice]):
    """``steps`` (td_steps' signature) for one group of runs after another: temporal cache
    blocking. A group's weights stay in the CPU's caches for the whole chunk instead of every
    step streaming all runs' weights from L3. Each group gets views of its runs (actor.slice_runs,
    env.slice_runs, slices of the per-run arguments), so its updates land in the whole batch; runs are
    independent, so the grouping does not change what a run computes."""

    def by_groups(actor, env, generator, s, a, F_sa, x_sa, alive, lrs, betas, uniforms, *inputs):
        parts = [
            steps(
                actor.slice_runs(g),
                env.slice_runs(g),
                generator,
                s[g],
                a[g],
                F_sa[g],
                x_sa[g],
                alive[g],
                lrs,
                betas,
                uniforms[:, g],
                *(x[:, g] for x in inputs),
            )
            for g in groups
        ]
        return TDChunk(*(torch.cat(outs, RUN_AXIS[field]) for field, outs in zip(TDChunk._fields, zip(*parts))))

    return by_groups


def generic_inputs(args: tuple) -> tuple:
    """td_steps' arguments with the environment's inputs generic in every size after (step, run):
    sizes that a configuration sets, such as the floor's noisy pixels a step (round(noise · 784),
    §3.4), so that a sweep over the noise level compiles one graph, not one per level."""
    return (*args[:TD_STEPS_FIXED], *(size_generic(x, 2) for x in args[TD_STEPS_FIXED:]))


def compiled_td_steps(n_runs: int, group_runs: int, device: torch.device):
    """td_steps as one compiled graph per chunk (``ferl.compiled``), generic in the environment's
    per-step input sizes (``generic_inputs``); on a CPU run by groups of ``group_runs`` runs (a
    smaller last group compiles a second graph)."""
    steps = compiled(td_steps, device, "a chunk of TD steps", generic=generic_inputs)
    if device.type != "cpu" or n_runs <= group_runs:
        return steps
    return td_steps_by_groups(steps, [slice(r, min(r + group_runs, n_runs)) for r in range(0, n_runs, group_runs)])


def chunk_length(steps: int, *intervals: int, most: int = MAX_CHUNK) -> int:
    """The longest chunk ≤ ``most`` (a divisor of MAX_CHUNK) that divides the run length and every
    interval, so logging and periodic checkpoints fall on chunk ends."""
    return math.gcd(most, steps, *intervals)


@contextmanager
def switch_interval(seconds: float):
    """Python's GIL switch interval set to ``seconds`` inside the block."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def done_future(value) -> Future:
    """A future that already holds ``value``."""
    future: Future = Future()
    future.set_result(value)
    return future
