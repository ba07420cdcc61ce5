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

from ferl.compiled import compiled, unroll_chunk
from ferl.interfaces import TrainingBatchBase
from ferl.predictors.heads import clean, valid_steps

# SGD steps per compiled chunk: 8 at T = 7 compiles in ~40 s (16: ~80 s) and leaves the call's
# guards and launch ~1/8 of an update; fewer where the sequences are long (``unroll_chunk``)
CHUNK_STEPS = 8


def sgd_steps(
    members: list, memory: list, params: list, y, a, rs: list, steps, reward_steps, lr: float, B: int
) -> None:
    """Plain SGD steps θ ← θ − α ∇_θ J, one on every B consecutive sequences of y (R', K·B, T+1, Y),
    a, rs[k], steps and reward_steps (the weight of every step in its update's loss), for the
    members stacked along the run axis (``PredictorBatch``); ``memory`` their memory parameters,
    ``params`` everything trained (memory first), updated in place."""
    for i in range(0, y.shape[1], B):
        s = slice(i, i + B)
        grads = type(members[0]).bptt(
            members,
            memory,
            y[:, s],
            a[:, s],
            [r[:, s] if r is not None else None for r in rs],
            steps[:, s],
            reward_steps[:, s],
        )
        torch._foreach_add_(params, grads, alpha=-lr)


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
        self.unroll_to: int | None = None

    def fuse(self, device: torch.device, unroll_to: int | None = None) -> None:
        """Train in compiled chunks of CHUNK_STEPS SGD steps (``ferl.compiled``) where the class's
        BPTT is written out in tensor operations (``traceable_bptt``). Every step then unrolls the
        longest training sequence (or ``unroll_to`` actions: one graph for batches whose longest
        sequence varies, as the online trainer's replays), the shorter ones masked, and a short
        last chunk is filled with sequences of weight 0, whose gradients are exactly 0: the same
        steps as eager, up to the rounding of the generated kernels (tests/test_fast_path.py)."""
        if type(self.lead).traceable_bptt:
            self.chunk, self.unroll_to = compiled_chunk(device), unroll_to

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
        if self.chunk is not None:
            T = self.unroll_to if self.unroll_to is not None else int(L.max())
            self.train_chunks(memory, params, order, steps, reward_steps, T)
        else:
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
