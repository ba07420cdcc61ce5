"""Random numbers for many future steps drawn in one go.

A training step needs a few random numbers per run; drawing them with one small RNG call
each costs more than the arithmetic of the step. Here they are drawn ``block`` steps at a
time from the run batch's generator and handed out step by step; the stream is a pure
function of the generator state, so results stay reproducible and resumable.
"""

import torch


def random_subsets(rows: int, n: int, k: int, generator: torch.Generator) -> torch.Tensor:
    """Uniformly random k-subsets of range(n), one per row: (rows, k) indices.

    Floyd's algorithm (Bentley & Floyd 1987): for draw i = 0 … k−1, j = n−k+i, draw t uniform in
    [0, j] and take t, or j if t was already taken. Exact, k random numbers per row. Vectorised
    over the draws too: t_i was taken before draw i iff an earlier draw had the same t, or t_i is
    the j of an earlier draw l that found its own t_l taken (and so took j_l). That second case
    links i to l < i; following the links to a fixed point takes a few rounds, as a link needs
    t_i ≥ n−k. The picks equal the draw-by-draw algorithm's (tests/test_random_blocks.py).
    """
    device = generator.device
    u = torch.rand(rows, k, generator=generator, device=device, dtype=torch.float64)
    bounds = torch.arange(n - k, n, device=device)  # j of every draw
    # t of every draw; j + 1 as float64 (multiplying by an integer tensor takes a slow path)
    t = torch.minimum(u.mul_(torch.arange(n - k + 1, n + 1, dtype=u.dtype, device=device)).long(), bounds)
    draws = torch.arange(k, dtype=torch.int16, device=device)  # k ≤ n pixels < 2^15
    first = torch.full((rows, n), k, dtype=torch.int16, device=device).scatter_reduce_(
        1, t, draws.expand(rows, k), "amin"
    )  # the first draw of every value
    repeated = first.gather(1, t) < draws
    linked = (t >= n - k) & (t < bounds)  # t is the j of the earlier draw t − (n − k)
    earlier = (t - (n - k)).clamp_(min=0)
    taken = repeated
    while True:
        grown = repeated | (linked & taken.gather(1, earlier))
        if torch.equal(grown, taken):
            return torch.maximum(t, bounds * taken, out=t)  # j where t was taken (j ≥ t)
        taken = grown


class Blocks:
    """Hands out per-step slices of tensors that ``draw(steps)`` makes for ``steps`` steps at once."""

    def __init__(self, draw, steps_per_block: int):
        self.draw, self.steps_per_block = draw, steps_per_block
        self.buffers: tuple[torch.Tensor, ...] | None = None
        self.cursor = steps_per_block  # at a block's end: the first take draws

    def next(self):
        """One step's tensors."""
        return tuple(b[0] for b in self.take(1))

    def take(self, steps: int):
        """The next ``steps`` steps' tensors, stacked: the same numbers ``steps`` calls of
        ``next`` would hand out, across block boundaries too."""
        pieces = []
        while steps:
            if self.cursor == self.steps_per_block:
                self.buffers, self.cursor = self.draw(self.steps_per_block), 0
            assert self.buffers is not None  # drawn above: the cursor starts at a block's end
            n = min(steps, self.steps_per_block - self.cursor)
            pieces.append(tuple(b[self.cursor : self.cursor + n] for b in self.buffers))
            self.cursor, steps = self.cursor + n, steps - n
        return pieces[0] if len(pieces) == 1 else tuple(torch.cat(parts) for parts in zip(*pieces))

    def state_dict(self) -> dict:
        return {"buffers": self.buffers, "cursor": self.cursor}

    def load_state_dict(self, state: dict, device) -> None:
        self.cursor = state["cursor"]
        self.buffers = None if state["buffers"] is None else tuple(b.to(device) for b in state["buffers"])


def steps_per_block(numbers_per_step: int, budget: int = 1 << 18) -> int:
    """How many steps of random numbers fit a block of about ``budget`` numbers."""
    return max(1, budget // max(1, numbers_per_step))
