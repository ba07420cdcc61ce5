"""Pattern-mode BPTT training of predictors, batched over runs and over predictors (§4.3.1, §5.2).

One SGD step per sequence (``batch_size`` = 1, the dissertation's pattern mode) or per
``batch_size`` sequences on their mean loss, every run on its own sequence order. Predictors that
share the form of the memory (their ``batch_key``: chapter 5's observation and reward predictors)
train as one batch along the run axis: their memories unroll and backpropagate in the same
batched products (the predictor class's ``bptt``), only the output heads apart. Every predictor
still takes its own order and its own plain SGD steps, so each one's training equals training it
alone (tested).
"""

import functools
from collections.abc import Callable

import torch
import torch.nn.functional as F

from ferl.compiled import MAX_UNROLLED_STEPS, compiled, in_chunks, unroll_chunk
from ferl.interfaces import TrainingBatchBase
from ferl.predictors.heads import clean, members_heads, valid_steps

# SGD steps per compiled chunk: 8 at T = 7 compiles in ~40 s (16: ~80 s) and leaves the call's
# guards and launch ~1/8 of an update; fewer where the sequences are long (``unroll_chunk``)
CHUNK_STEPS = 8
# Sequences longer than this train by BPTT in compiled chunks of time steps (``chunked_bptt``),
# one graph for every length, where the memory splits its unroll (``time_chunks``); up to it, in
# graphs of whole SGD steps, every step unrolled (``MAX_UNROLLED_STEPS`` a graph). The chunks compile
# in ~6 s at any length, the unrolled SGD step in ~96 s at 21 steps, but the chunks ran an online
# replay 2.7 × slower once compiled (docs/performance.md, "The online trainer's episodes and its
# replay over long sequences"), so they take only the lengths that one graph may not unroll
TIME_CHUNKED_FROM = MAX_UNROLLED_STEPS


def sgd_steps(
    members: list, memory: list, params: list, y, a, rs: list, steps, reward_steps, lr: float, B: int, bptt=None
) -> None:
    """Plain SGD steps θ ← θ − α ∇_θ J, one on every B consecutive sequences of y (R', K·B, T+1, Y),
    a, rs[k], steps and reward_steps (the weight of every step in its update's loss), for the
    members stacked along the run axis (``PredictorBatch``); ``memory`` their memory parameters,
    ``params`` everything trained (memory first), updated in place. ``bptt``: the gradients, by
    default the members' class's ``bptt``."""
    for i in range(0, y.shape[1], B):
        s = slice(i, i + B)
        grads = (bptt or type(members[0]).bptt)(
            members,
            memory,
            y[:, s],
            a[:, s],
            [r[:, s] if r is not None else None for r in rs],
            steps[:, s],
            reward_steps[:, s],
        )
        torch._foreach_add_(params, grads, alpha=-lr)


def memory_steps(predictor, params: list, x: torch.Tensor, state: torch.Tensor) -> tuple:
    """``predictor.run_steps``: the function that one graph of time steps compiles (``chunked_bptt``)."""
    return predictor.run_steps(params, x, state)


@functools.cache
def compiled_memory_steps(device: torch.device) -> Callable[..., tuple]:
    """``memory_steps`` compiled once per device, for chunks of ``ferl.compiled.CHUNK_STEPS`` steps."""
    return compiled(memory_steps, device, "a chunk of time steps of BPTT")


def chunked_bptt(steps_fn: Callable, members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
    """The gradients that the members' class's ``bptt`` gives (the same arguments), for a memory
    that splits its unroll (``time_chunks``): the memory's steps run in chunks of a fixed number of
    steps (``ferl.compiled.in_chunks`` calling ``steps_fn``: ``memory_steps`` or its compiled
    graph), the state carried from chunk to chunk; the heads' part is written out
    (``members_heads``, Eqs. 2.57–2.62), which gives ∂J/∂m_t, and autograd takes it back through
    the chunks (their compiled backward graphs) to the memory's parameters (BPTT, §2.4.1). The
    graph of a chunk is the same for every sequence length."""
    lead = members[0]
    with torch.enable_grad():
        leaves = [q.detach().requires_grad_() for q in memory]
        x, state, m_0 = lead.sequence_start(leaves, y, a)
        m_t = in_chunks(lambda x_chunk, carried: steps_fn(lead, leaves, x_chunk, carried), x, state)
        m = torch.cat([m_0.unsqueeze(2), m_t], 2)  # m_0 … m_T (R', B, T+1, M)
    heads, dm = members_heads(members, m.detach(), y, rs, steps, reward_steps)
    return list(torch.autograd.grad(m, leaves, dm)) + heads


@functools.cache
def compiled_chunk(device: torch.device) -> Callable[..., None]:
    """``sgd_steps`` compiled once per device: every batch of a run (the online trainer builds one
    after each episode) calls the same graph, whose guards pick it up again."""
    return compiled(sgd_steps, device, "SGD steps of BPTT")


class PredictorBatch(TrainingBatchBase):
    """Predictors with one ``batch_key`` and their training sequences (``Predictor.training_batch``)."""

    def __init__(self, predictors: list, y, a, rs: list, lengths, batch_size: int | None = None, summed: bool = False):
        """Members and their training sequences: y (R, N, T+1, Y), a (R, N, T, A), lengths (R, N)
        shared, targets rs[k] (R, N, T+1, ·) or None per member; the padding is zeroed once here.
        ``batch_size``: sequences per SGD step, the members' own ``batch_size`` unless given;
        ``summed``: a step on their summed loss (the first-order sum of as many pattern-mode
        steps) instead of their mean."""
        if len({p.batch_key for p in predictors}) != 1:
            raise ValueError(
                "a PredictorBatch needs predictors with the same memory, gains, lr, objective and batch size"
            )
        self.members = list(predictors)
        self.lead = predictors[0]
        self.batch_size, self.summed = batch_size or self.lead.batch_size, summed
        y, a, _ = clean(y, a, None, lengths)
        valid = valid_steps(lengths, y.shape[2]).unsqueeze(-1)
        # contiguous, so that a run's sequences are rows of one flattened view (``sequences``)
        self.y, self.a, self.lengths = y.contiguous(), a.contiguous(), lengths
        # where each row's run starts in the data's (run, sequence) axes flattened, (P·R, 1): the
        # members stacked along the run axis, as their memories are while training
        runs = torch.arange(lengths.shape[0], device=lengths.device).repeat(len(predictors))
        self.first_rows = (runs * lengths.shape[1]).unsqueeze(1)
        self.rs = [torch.where(valid, r, 0.0).contiguous() if r is not None else None for r in rs]
        self.chunk: Callable[..., None] | None = None  # sgd_steps compiled for chunks of CHUNK_STEPS steps (``fuse``)
        self.time_chunk: Callable[..., tuple] | None = None  # memory_steps compiled, where time_chunks (``fuse``)
        self.unroll_to: int | None = None

    def fuse(self, device: torch.device, unroll_to: int | None = None) -> None:
        """Train in compiled chunks of CHUNK_STEPS SGD steps (``ferl.compiled``) where the class's
        BPTT is written out in tensor operations (``traceable_bptt``). Every step then unrolls the
        longest training sequence (or ``unroll_to`` actions: one graph for batches whose longest
        sequence varies, as the online trainer's replays), the shorter ones masked, and a short
        last chunk is filled with sequences of weight 0, whose gradients are exactly 0: the same
        steps as eager, up to the rounding of the generated kernels (tests/test_fast_path.py).
        Sequences longer than TIME_CHUNKED_FROM, of a memory that splits its unroll, train step by
        step instead, by BPTT in compiled chunks of time steps (``chunked_bptt``), each sequence cut
        to the longest of its step: one graph for every length."""
        if type(self.lead).traceable_bptt:
            self.chunk, self.unroll_to = compiled_chunk(device), unroll_to
        if type(self.lead).time_chunks:
            self.time_chunk = compiled_memory_steps(device)

    @torch.no_grad()
    def train_epoch(self, orders: list) -> None:
        """One epoch of every member, member k taking the sequences in its order orders[k] (R, N),
        a permutation of each run's N sequences: for i = 1 … N every run takes a plain SGD step
        θ ← θ − α ∇_θ J on its sequence orders[k][:, i] (or on the mean over the next B). Runs
        share nothing: each run's parameters move by the gradient of its own loss alone."""
        p, P, R = self.lead, len(self.members), self.lengths.shape[0]
        order = torch.cat(orders) if P > 1 else orders[0]  # (P·R, N): the members' orders stacked
        L = self.lengths.flatten()[self.first_rows + order]
        # the memories' parameters of all members in one (P·R, …) tensor each while training
        memory = (
            p.memory_parameters()
            if P == 1
            else [torch.cat(qs) for qs in zip(*(q.memory_parameters() for q in self.members))]
        )
        params = memory + [q for member in self.members for q in member.head_parameters()]
        B, n = self.batch_size, L.shape[1]
        # the weight of every step in its update's loss: 1/(T+1) under J(T), over the sequences
        # of the update (B, fewer in a last short one) unless summed, 0 on padding; rewards from t = 1
        chunk = torch.arange(n, device=L.device) // B
        scale = 1.0 / (L + 1).to(self.y.dtype) if p.time_average else torch.ones_like(L, dtype=self.y.dtype)
        if not self.summed:
            scale = scale / chunk.bincount()[chunk]
        steps = valid_steps(L, self.y.shape[2]) * scale.unsqueeze(-1)
        reward_steps = steps * (torch.arange(self.y.shape[2], device=L.device) > 0)
        fused = self.chunk is not None or self.time_chunk is not None
        T = (self.unroll_to if self.unroll_to is not None else int(L.max())) if fused else 0
        in_time = self.time_chunk is not None and T > TIME_CHUNKED_FROM
        if self.chunk is not None and not in_time:
            self.train_chunks(memory, params, order, steps, reward_steps, T)
        else:
            # in chunks of time steps (long sequences, fused) or the class's own (eager)
            bptt = functools.partial(chunked_bptt, self.time_chunk) if self.time_chunk and in_time else None
            y, a, rs = self.sequences(order, slice(None), self.y.shape[2] - 1)
            # T of every step: the longest sequence of its B positions over all runs, read once (one
            # host sync per epoch); it trims the padding all runs and sequences of the step share
            longest = F.pad(L.max(0).values, (0, -n % B)).view(-1, B).max(1).values.tolist()
            for i, T in zip(range(0, n, B), longest):
                s = slice(i, i + B)
                sgd_steps(
                    self.members,
                    memory,
                    params,
                    y[:, s, : T + 1],
                    a[:, s, :T],
                    [r[:, s, : T + 1] if r is not None else None for r in rs],
                    steps[:, s, : T + 1],
                    reward_steps[:, s, : T + 1],
                    p.lr,
                    B,
                    bptt,
                )
        if P > 1:
            for k, member in enumerate(self.members):
                for q, merged in zip(member.memory_parameters(), memory):
                    q.copy_(merged[k * R : (k + 1) * R])

    def sequences(self, order: torch.Tensor, s: slice, T: int) -> tuple:
        """The sequences at positions ``s`` of the members' stacked orders ``order`` (P·R, N), cut to
        T actions: y (P·R, ·, T+1, Y) and a (P·R, ·, T, A), stacked along the run axis as the
        members' memories are, and each member's targets (R, ·, T+1, ·) or None."""
        at = order[:, s]
        R, S = self.lengths.shape[0], at.shape[1]
        rows = (self.first_rows + at).flatten()

        def take(x: torch.Tensor, steps: int, part: slice = slice(None)) -> torch.Tensor:
            # whole sequences by index_select, a copy of contiguous blocks: ~3× faster than x[runs, at]
            picked = x[:, :, :steps].flatten(0, 1).index_select(0, rows[part])
            return picked.view(-1, S, *picked.shape[1:])

        targets = [
            take(r, T + 1, slice(k * R * S, (k + 1) * R * S)) if r is not None else None for k, r in enumerate(self.rs)
        ]
        return take(self.y, T + 1), take(self.a, T), targets

    def train_chunks(self, memory: list, params: list, order: torch.Tensor, steps, reward_steps, T: int) -> None:
        """The epoch's steps in compiled chunks of CHUNK_STEPS, every sequence unrolled to T actions,
        each chunk's sequences gathered as it starts: the whole epoch's, gathered at once, were
        larger than the caches (the digit maze's 784 pixels: ~80 MB, half an epoch). The last
        chunk is filled with sequences of weight 0, whose gradients are exactly 0."""
        assert self.chunk is not None  # train_epoch calls this only once fused
        B, n = self.batch_size, steps.shape[1]
        # fewer steps a graph where sequences are long, and no more than the epoch has
        size = unroll_chunk(T, min(CHUNK_STEPS, -(-n // B))) * B
        pad = -n % size
        order = F.pad(order, (0, pad))  # the fill: the first sequence, weighted 0 below
        steps, reward_steps = (F.pad(x[:, :, : T + 1], (0, 0, 0, pad)) for x in (steps, reward_steps))
        for i in range(0, n + pad, size):
            s = slice(i, i + size)
            y, a, rs = self.sequences(order, s, T)
            self.chunk(self.members, memory, params, y, a, rs, steps[:, s], reward_steps[:, s], self.lead.lr, B)
