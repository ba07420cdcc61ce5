"""Random numbers drawn in blocks (ferl/random_blocks.py): chunks of steps see the same stream
as step-by-step draws, and Floyd's subsets are uniform."""

import itertools
import math

import pytest
import torch

from ferl.random_blocks import Blocks, random_subsets


def counting_blocks(steps_per_block: int) -> Blocks:
    """Blocks whose numbers are the step index itself (two tensors per step)."""
    drawn = itertools.count()

    def draw(steps):
        start = next(drawn) * steps
        ids = torch.arange(start, start + steps)
        return ids, -ids

    return Blocks(draw, steps_per_block)


@pytest.mark.parametrize("chunks", [[1] * 20, [3, 4, 5, 8], [7, 13], [20]])
def test_take_hands_out_the_steps_next_would_across_block_boundaries(chunks):
    one, many = counting_blocks(6), counting_blocks(6)
    singles = [one.next() for _ in range(sum(chunks))]
    taken = [many.take(k) for k in chunks]
    ids = torch.cat([t[0] for t in taken])
    assert ids.tolist() == [s[0].item() for s in singles] == list(range(sum(chunks)))
    assert torch.equal(torch.cat([t[1] for t in taken]), -ids)


def test_take_resumes_from_a_state_dict_mid_block():
    whole, cut = counting_blocks(5), counting_blocks(5)
    expected = torch.cat([whole.take(3)[0], whole.take(4)[0]])
    first = cut.take(3)[0]
    copy = counting_blocks(5)
    copy.load_state_dict(cut.state_dict(), "cpu")
    copy.draw = cut.draw  # the generator state travels with it in a real checkpoint
    assert torch.equal(torch.cat([first, copy.take(4)[0]]), expected)


def test_random_subsets_are_distinct_and_uniform():
    n, k, rows = 6, 3, 20_000
    chosen = random_subsets(rows, n, k, torch.Generator().manual_seed(0))
    assert all(len(set(r)) == k for r in chosen.tolist())
    counts = torch.bincount(chosen.flatten(), minlength=n).double() / rows
    assert torch.allclose(counts, torch.full((n,), k / n, dtype=torch.float64), atol=0.01)
    subsets = {tuple(sorted(r)) for r in chosen.tolist()}
    assert len(subsets) == math.comb(n, k)


@pytest.mark.parametrize(
    "n, k, rows", [(784, 98, 300), (30, 20, 2000), (6, 3, 500), (5, 5, 50), (10, 1, 50), (4, 0, 5)]
)
def test_random_subsets_are_floyds_draw_by_draw_picks(n, k, rows):
    """The vectorised resolution picks what Floyd's loop picks from the same uniforms, in order."""
    u = torch.rand(rows, k, generator=torch.Generator().manual_seed(n + k), dtype=torch.float64)
    expected = []
    for row in u.tolist():
        taken = []
        for i, x in enumerate(row):
            j = n - k + i
            t = min(int(x * (j + 1)), j)
            taken.append(j if t in taken else t)
        expected.append(taken)
    chosen = random_subsets(rows, n, k, torch.Generator().manual_seed(n + k))
    assert chosen.tolist() == expected
