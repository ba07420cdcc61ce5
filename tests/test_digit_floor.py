"""Digit-floor environment (§3.4): rewards, torus moves, transport, noise, optimal tables."""

import numpy as np
import pytest
import torch

from ferl.data import MnistSplit, add_pixel_noise, pixel_noise, pixel_noise_draws, with_pixel_noise
from ferl.envs.digit_floor import DigitFloor, optimal_policy, patch_rewards

N, E, S, W = range(4)


def tiny_split(per_class=20, seed=0):
    """Synthetic 'MNIST': every image of class c has its pixels at value (c + 1) / 20, so the
    class of an observed clean tile is readable from its pixels."""
    labels = torch.arange(10).repeat_interleave(per_class)
    images = ((labels.float() + 1) / 20).unsqueeze(1).expand(-1, 784).clone()
    images[:, 0] = torch.rand(len(labels), generator=torch.Generator().manual_seed(seed))  # distinct images
    return MnistSplit(images, labels, images.clone(), labels.clone())


def class_of(obs):
    return [str(round(v * 20 - 1)) for v in obs[:, 1].tolist()]


def make_env(R=4, **kw):
    return DigitFloor(R, tiny_split(), torch.Generator().manual_seed(0), noise=0.0, **kw)


def put(env, row, col):
    side = 3 * 4
    env.tile = torch.full((env.n_runs,), row * side + col, dtype=torch.long)


def test_cw_rewards_from_definition():
    table = patch_rewards("cw")
    cw_moves = {(0, E), (1, E), (2, S), (5, S), (8, W), (7, W), (6, N), (3, N)}
    into_goal = {(1, S), (3, E), (5, W), (7, N)}
    for p in range(9):
        for a in range(4):
            expected = 10 if (p, a) in into_goal else 4 if (p, a) in cw_moves else -2
            if p == 4:
                expected = -2
            assert table[p, a] == expected, (p, a)


def test_ccw_is_reversed_cycle_and_none_is_silent():
    ccw = patch_rewards("ccw")
    assert ccw[1, W] == 4 and ccw[0, S] == 4 and ccw[0, E] == -2 and ccw[1, S] == 10
    assert not patch_rewards("none").any()


@pytest.mark.parametrize(
    "condition,expected",
    [
        ("cw", {0: E, 1: S, 2: S, 3: E, 5: W, 6: N, 7: N, 8: W}),
        ("ccw", {0: S, 1: S, 2: W, 3: E, 5: W, 6: E, 7: N, 8: N}),
    ],
)
def test_optimal_action_tables(condition, expected):
    _, action, rate = optimal_policy(patch_rewards(condition))
    assert {p: int(action[p]) for p in range(9) if p != 4} == expected
    assert action[4] == -1
    assert rate == pytest.approx(8.0)  # ((4 + 10) + 10) / (2 + 1), §3.5.1 footnote 4


def test_step_rewards_moves_and_torus_wrap():
    env = make_env(R=1)
    put(env, 0, 0)  # class "0" of the top-left patch
    obs, r, *_ = env.step(torch.tensor([E]))
    assert r.item() == 4 and class_of(obs) == ["1"]
    obs, r, *_ = env.step(torch.tensor([N]))  # from "1" north leaves the patch: row 0 → row 11 ("7")
    assert r.item() == -2 and class_of(obs) == ["7"] and env.tile.item() == 11 * 12 + 1
    put(env, 11, 11)  # "8" in the bottom-right corner: east wraps to column 0 ("6")
    obs, r, *_ = env.step(torch.tensor([E]))
    assert r.item() == -2 and class_of(obs) == ["6"] and env.tile.item() == 11 * 12 + 0
    obs, r, *_ = env.step(torch.tensor([S]))  # south wraps to row 0 ("0")
    assert class_of(obs) == ["0"] and env.tile.item() == 0


def test_goal_transports_to_uniform_non_goal_tile():
    env = DigitFloor(20_000, tiny_split(), torch.Generator().manual_seed(1), noise=0.0)
    put(env, 1, 0)  # "3", moving east enters the goal
    obs, r, *_ = env.step(torch.full((env.n_runs,), E))
    assert (r == 10).all()
    classes = class_of(obs)
    assert "4" not in classes
    counts = np.array([classes.count(c) for c in "01235678"]) / env.n_runs
    np.testing.assert_allclose(counts, 1 / 8, atol=0.01)
    assert len(set(env.tile.tolist())) > 100  # anywhere on the floor, not just this patch


def test_each_tile_has_its_own_training_image_of_its_class():
    env = make_env(R=3)
    ids = env.tile_image
    for r in range(3):
        assert len(set(ids[r].tolist())) == ids.shape[1]  # distinct images (20 per class ≥ 16 tiles)
    labels = tiny_split().train_labels[ids]
    expected = torch.tensor([int(env.layout[p]) for p in env.tile_position.tolist()])
    assert (labels == expected).all()
    assert not torch.equal(ids[0], ids[1])  # every run has its own floor


def test_noise_tile_replaces_class_with_independent_noise_images():
    env = make_env(R=2, noise_tile="5")
    assert env.classes == ["0", "1", "2", "3", "4", "6", "7", "8", "N"]
    n_tiles = env.tile_image[:, env.tile_position == 5]
    images = env.bank[n_tiles.flatten()]
    assert len(n_tiles.flatten().unique()) == n_tiles.numel()
    assert images.std() > 0.25  # U(0,1) has std 0.289; digit images here are constant


@pytest.mark.parametrize("noise", [0.0, 0.125, 0.5, 1.0])
def test_exact_noise_pixel_count(noise):
    clean = torch.full((50, 784), 2.0)  # out of [0, 1], so a replaced pixel is recognisable
    noisy = add_pixel_noise(clean, noise, torch.Generator().manual_seed(0))
    changed = (noisy != clean).sum(1)
    assert (changed == round(noise * 784)).all()
    assert ((noisy[noisy != 2.0] >= 0) & (noisy[noisy != 2.0] <= 1)).all()


@pytest.mark.parametrize("noise", [0.0, 0.125, 0.5])
def test_floor_noise_up_to_half_is_drawn_as_before(noise):
    """Up to half the pixels noisy, the floor draws the same numbers as ``pixel_noise`` (its random
    stream, and so the reproduction's default floor, is unchanged). At noise 0 nothing is drawn;
    what is handed on has no size 0 (two positions whose NaN values keep the image)."""
    mine, theirs = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    got = pixel_noise_draws(30, 784, noise, mine)
    want = pixel_noise(30, 784, noise, theirs)
    assert torch.equal(mine.get_state(), theirs.get_state())
    if noise == 0:
        assert want[0].shape == (30, 0) and got[0].shape == got[1].shape == (30, 2)
        assert got[1].isnan().all()
        return
    for g, w in zip(got, want):
        assert torch.equal(g, w)


@pytest.mark.parametrize("noise", [0.0, 0.125, 0.5, 0.5 + 1 / 784, 0.75, 1.0])
def test_floor_noise_replaces_a_uniform_subset_of_exactly_k_pixels(noise):
    """Either way of drawing (the noisy pixels up to half, the clean ones above) replaces exactly
    k = round(noise · 784) pixels of every image by values in [0, 1), leaves the others as they
    were, and replaces every pixel equally often: each pixel's count over 4 000 images is within
    5 s.d. of the binomial mean 4 000 · k/784 (a pixel's count is Binomial(4000, k/784))."""
    rows, n = 4000, 784
    clean = torch.full((rows, n), 2.0)  # out of [0, 1], so a replaced pixel is recognisable
    idx, values = pixel_noise_draws(rows, n, noise, torch.Generator().manual_seed(0))
    noisy = with_pixel_noise(clean.clone(), idx, values)
    k = round(noise * n)
    replaced = noisy != 2.0
    assert (replaced.sum(1) == k).all()
    assert ((noisy[replaced] >= 0) & (noisy[replaced] < 1)).all()
    p = k / n
    counts = replaced.sum(0).double()
    assert (counts - rows * p).abs().max() <= 5 * (rows * p * (1 - p)) ** 0.5 + 1e-9
    if 0 < k:
        assert abs(noisy[replaced].mean().item() - 0.5) < 0.01  # U(0, 1): s.e. of the mean ≤ 0.005


@pytest.mark.parametrize("noise", [0.0, 0.25, 0.75, 1.0])
def test_floor_noise_compiled_equals_eager(noise):
    """``with_pixel_noise`` compiled with generic sizes (as the floor's chunk is) gives the eager
    result exactly, on both sides of half the pixels and at both ends."""
    images = torch.rand(6, 784, generator=torch.Generator().manual_seed(1))
    idx, values = pixel_noise_draws(6, 784, noise, torch.Generator().manual_seed(2))
    compiled = torch.compile(with_pixel_noise, dynamic=True, fullgraph=True)
    assert torch.equal(compiled(images.clone(), idx, values), with_pixel_noise(images.clone(), idx, values))


def test_noise_is_fresh_at_every_observation():
    env = DigitFloor(1, tiny_split(), torch.Generator().manual_seed(0), noise=0.125)
    a, b = env.observe(), env.observe()
    assert not torch.equal(a, b)
