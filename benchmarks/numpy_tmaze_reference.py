"""Plain per-step, single-run NumPy reference of the T-maze agent (Algorithm 1, chapter 4).

The *speed reference* that the batched torch implementation (``ferl/trainers/actor_episodes.py``,
``ferl/predictors/``, ``ferl/actors/free_energy.py``) is compared against: one Python iteration per
environment step (actor phase) or per sequence (predictor training), one run, numpy-vectorised
over nodes only.  No torch.

Algorithm (Otsuka's dissertation, §4.2–4.3; Bakker 2002):

* T-maze: corridor of T_min cells from the start to the T-junction, goals left and right.
  Actions N E S W; rewards ±5 at the rewarded / other goal (terminal), −1 for a wall bump (no
  move), −0.1 otherwise; cut off after T_max actions.  Matching maze: signals s0 at the start and
  s1 at the junction, s0 = s1 rewards the right goal.  Observations: 7 bits (5 position + 2
  signal bits).
* joint Elman predictor (Eqs. 4.1–4.6): m_0 = σ(β_m b_init),
  m_t = σ(β_m (W_my c_y y_{t−1} + W_ma c_a a_{t−1} + W_mm m_{t−1} + b_m)),
  ŷ_t = σ(β_y (W_ym m_t + b_y)), r̂_t = σ(β_r (W_rm m_t + b_r)) (4 reward bits) or
  W_rm m_t + b_r (linear scalar reward, Eq. 5.2); trained by hand-written BPTT (§2.4.1) in
  pattern mode, one SGD step per sequence, on Σ_t E_t or its time average J(T).
* actor: FERL RBM on the state (y_t, m_t) with one-hot action nodes; Q = −F; softmax policy with
  inverse temperature β (Eq. 3.11) linear 0 → 10 over the episodes; SARSA(0) online update
  (Eq. 3.10) with α / √(fan-in of a hidden node) (conf/actor/ferl_tmaze.yaml, lr_norm=fan_in),
  F(s_t, a_t) of the TD error at the current parameters (td_fresh).

Parameter layouts follow the torch modules without the run axis: predictor weights (out, in),
actor W_sh (S, H), W_ah (A, H).

    python benchmarks/numpy_tmaze_reference.py --episodes 2000
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.numpy_reference import sample_action  # the floor reference's softmax draw

N_ACTIONS = 4
N, E, S, W = range(N_ACTIONS)
N_OBS = 7  # start, corridor, junction, goal_left, goal_right, signal 0, signal 1
REWARD_VALUES = (-5.0, -1.0, -0.1, 5.0)  # sorted: the order of the reward bits
N_REWARD = len(REWARD_VALUES)
JOINT = dict(
    c_y=1.0, c_a=1.0, beta_m=1.0, beta_y=1.0, beta_r=1.0, rho_y=1.0, rho_r=4.0, reward_output="bits", time_average=True
)  # conf/predictor/joint.yaml

# ----------------------------------------------------------------------------
# Environment
# ----------------------------------------------------------------------------


def env_step(position: int, action: int, right_rewarded: bool, corridor_length: int, goal=5.0, wall=-1.0, step=-0.1):
    """(new position, reward, terminated) of one action.  Positions 0 … T_min − 1 run up the
    corridor, T_min / T_min + 1 are the left / right goal."""
    junction = corridor_length - 1
    if action == N and position < junction:
        return position + 1, step, False
    if action == S and position > 0:
        return position - 1, step, False
    if position == junction and action in (E, W):
        right = action == E
        return corridor_length + right, (goal if right == right_rewarded else -goal), True
    return position, wall, False


def observation(position: int, s0: int, s1: int, corridor_length: int, matching: bool) -> np.ndarray:
    """7-bit observation: position bit (start, corridor, junction, goal_left, goal_right) and the
    signal bit shown there (s0 at the start, s1 at the junction of a matching maze)."""
    y = np.zeros(N_OBS)
    junction = corridor_length - 1
    if position == 0:
        y[0] = 1.0
        y[5 + s0] = 1.0
    elif position < junction:
        y[1] = 1.0
    elif position == junction:
        y[2] = 1.0
        if matching:
            y[5 + s1] = 1.0
    else:
        y[3 + position - corridor_length] = 1.0
    return y


# ----------------------------------------------------------------------------
# Elman predictor
# ----------------------------------------------------------------------------


def sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def softplus(x):
    return np.logaddexp(0.0, x)


def init_predictor(
    rng: np.random.Generator, n_obs=N_OBS, n_actions=N_ACTIONS, n_memory=20, n_reward=N_REWARD, init_std=1.0
) -> dict:
    shapes = dict(
        W_my=(n_memory, n_obs),
        W_ma=(n_memory, n_actions),
        W_mm=(n_memory, n_memory),
        b_m=(n_memory,),
        b_init=(n_memory,),
        W_ym=(n_obs, n_memory),
        b_y=(n_obs,),
        W_rm=(n_reward, n_memory),
        b_r=(n_reward,),
    )
    return {k: rng.normal(0.0, init_std, size=s) for k, s in shapes.items()}


def predictor_initial(P: dict, hp=JOINT) -> np.ndarray:
    """m_0 = σ(β_m b_init), Eq. (4.1)."""
    return sigmoid(hp["beta_m"] * P["b_init"])


def predictor_step(P: dict, m_prev, y_prev, a_prev, hp=JOINT) -> np.ndarray:
    """m_t of Eq. (4.3) (the actor phase needs only the memory)."""
    u = P["W_my"] @ (hp["c_y"] * y_prev) + P["W_ma"] @ (hp["c_a"] * a_prev) + P["W_mm"] @ m_prev + P["b_m"]
    return sigmoid(hp["beta_m"] * u)


def bptt(P: dict, y, a, r, hp=JOINT):
    """Loss and gradients of one sequence y (T+1, Y), a (T, A) one-hot, r (T+1, ·) (r[0] unused),
    by backpropagation through time (§2.4.1, Eqs. 2.57–2.63).  Returns (loss, grads)."""
    T = len(a)
    bm, by, br = hp["beta_m"], hp["beta_y"], hp["beta_r"]
    scale = 1.0 / (T + 1) if hp["time_average"] else 1.0
    # forward
    m = np.empty((T + 1, P["b_m"].size))
    m[0] = sigmoid(bm * P["b_init"])
    for t in range(1, T + 1):
        m[t] = predictor_step(P, m[t - 1], y[t - 1], a[t - 1], hp)
    z_y = by * (m @ P["W_ym"].T + P["b_y"])
    z_r = m[1:] @ P["W_rm"].T + P["b_r"]
    loss = hp["rho_y"] * (softplus(z_y) - y * z_y).sum()
    if hp["reward_output"] == "bits":
        z_r = br * z_r
        loss += hp["rho_r"] * (softplus(z_r) - r[1:] * z_r).sum()
        g_r = scale * hp["rho_r"] * br * (sigmoid(z_r) - r[1:])  # (T, n_r)
    else:
        loss += 0.5 * hp["rho_r"] * ((r[1:] - z_r) ** 2).sum()
        g_r = scale * hp["rho_r"] * (z_r - r[1:])
    g_y = scale * hp["rho_y"] * by * (sigmoid(z_y) - y)  # (T+1, Y)
    # output layers
    G = {"W_ym": g_y.T @ m, "b_y": g_y.sum(0), "W_rm": g_r.T @ m[1:], "b_r": g_r.sum(0)}
    dm = g_y @ P["W_ym"]
    dm[1:] += g_r @ P["W_rm"]
    # memory, t = T … 1
    g_u = np.zeros((T, m.shape[1]))
    for t in range(T, 0, -1):
        g_u[t - 1] = dm[t] * bm * m[t] * (1.0 - m[t])
        dm[t - 1] += P["W_mm"].T @ g_u[t - 1]
    G["W_my"] = g_u.T @ (hp["c_y"] * y[:T])
    G["W_ma"] = g_u.T @ (hp["c_a"] * a)
    G["W_mm"] = g_u.T @ m[:T]
    G["b_m"] = g_u.sum(0)
    G["b_init"] = dm[0] * bm * m[0] * (1.0 - m[0])
    return loss * scale, G


def bptt_epoch(P: dict, sequences, order, lr: float, hp=JOINT) -> None:
    """Pattern mode (§4.3.1): one SGD step θ ← θ − α ∇θ per sequence, in ``order``.
    ``sequences``: list of (y (T+1, Y), a (T, A), r (T+1, ·))."""
    for i in order:
        _, G = bptt(P, *sequences[i], hp)
        for k, g in G.items():
            P[k] -= lr * g


def random_sequences(n: int, rng: np.random.Generator, corridor_length=3, max_steps=10, matching=True, lengths=None):
    """Random-policy episodes as predictor sequences (y, a one-hot, r reward bits); with
    ``lengths`` only episodes whose number of actions is in it are kept."""
    out = []
    while len(out) < n:
        s0, s1 = int(rng.integers(2)), int(rng.integers(2))
        right = (s0 == s1) if matching else bool(s0)
        pos = 0
        ys, acts, rs = [observation(pos, s0, s1, corridor_length, matching)], [], [np.zeros(len(REWARD_VALUES))]
        for _ in range(max_steps):
            act = int(rng.integers(N_ACTIONS))
            pos, rew, done = env_step(pos, act, right, corridor_length)
            ys.append(observation(pos, s0, s1, corridor_length, matching))
            acts.append(np.eye(N_ACTIONS)[act])
            rs.append(np.array([float(rew == v) for v in REWARD_VALUES]))
            if done:
                break
        if lengths is None or len(acts) in lengths:
            out.append((np.array(ys), np.array(acts), np.array(rs)))
    return out


# ----------------------------------------------------------------------------
# FERL actor
# ----------------------------------------------------------------------------


def init_actor(rng: np.random.Generator, n_state: int, n_hidden=20, init_std=1.0):
    W_sh = rng.normal(0.0, init_std, size=(n_state, n_hidden))
    W_ah = rng.normal(0.0, init_std, size=(N_ACTIONS, n_hidden))
    return [W_sh, W_ah, np.zeros(n_state), np.zeros(N_ACTIONS), np.zeros(n_hidden)]


def free_energy_all_actions(s, W_sh, W_ah, b_s, b_a, b_h):
    """F(s, a) of every one-hot action a (A,) and the hidden inputs x (A, H)."""
    x = (s @ W_sh + b_h)[None, :] + W_ah
    return -(s @ b_s) - b_a - softplus(x).sum(axis=1), x


def td_error(r: float, F_sa: float, F_next_a: float, gamma: float, terminal: bool) -> float:
    """SARSA(0): δ = r − γ F(s', a') + F(s, a), no bootstrap at a terminal transition."""
    return r - (0.0 if terminal else gamma * F_next_a) + F_sa


def sarsa_update(params, s, a: int, h_hat, delta: float, alpha: float) -> None:
    """In place, Eq. (3.10): θ += α δ (−∂F(s, a)/∂θ)."""
    W_sh, W_ah, b_s, b_a, b_h = params
    g = alpha * delta
    gh = g * h_hat
    W_sh += np.outer(s, gh)
    W_ah[a] += gh
    b_s += g * s
    b_a[a] += g
    b_h += gh


def fresh_pair(s, a: int, h_hat, delta: float, alpha: float, s_next, a_next: int, F_next_a: float, x_next_a):
    """F(s', a') and x(s', a') after ``sarsa_update(params, s, a, h_hat, delta, alpha)`` from their
    values before it, by that update's rank-one effect (td_fresh, ferl/actor.py learn)."""
    g = alpha * delta
    overlap = float(s_next @ s) + float(a_next == a)
    x_new = x_next_a + (overlap + 1.0) * g * h_hat
    return F_next_a - g * overlap - float((softplus(x_new) - softplus(x_next_a)).sum()), x_new


# ----------------------------------------------------------------------------
# Actor phase
# ----------------------------------------------------------------------------


def run_numpy_tmaze_reference(
    episodes: int,
    seed=0,
    corridor_length=3,
    max_steps=10,
    matching=True,
    n_hidden=20,
    n_memory=20,
    gamma=0.95,
    lr=0.05,
    beta_start=0.0,
    beta_end=10.0,
    init_std=1.0,
    predictor=None,
    hp=JOINT,
    td_fresh=True,
) -> dict:
    """The actor phase of Algorithm 1 for one run: the state is (y_t, m_t) of a frozen joint
    predictor (random unless ``predictor`` parameters are given); ``td_fresh`` as the actor's
    key of that name (conf/actor/ferl_tmaze.yaml)."""
    rng = np.random.default_rng(seed)
    P = predictor if predictor is not None else init_predictor(rng, n_memory=n_memory)
    n_state = N_OBS + P["b_m"].size
    params = init_actor(rng, n_state, n_hidden, init_std)
    alpha = lr / math.sqrt(n_state + N_ACTIONS)  # lr_norm = fan_in
    eye = np.eye(N_ACTIONS)
    m0 = predictor_initial(P, hp)
    returns = np.empty(episodes)
    lengths = np.empty(episodes, dtype=np.int64)
    correct = np.empty(episodes, dtype=bool)
    agent_steps = 0

    t0 = time.perf_counter()
    for k in range(episodes):
        beta = beta_start + (beta_end - beta_start) * k / episodes
        s0, s1 = int(rng.integers(2)), int(rng.integers(2))
        right = (s0 == s1) if matching else bool(s0)
        pos = 0
        y, m = observation(pos, s0, s1, corridor_length, matching), m0
        s = np.concatenate([y, m])
        F_all, x = free_energy_all_actions(s, *params)
        a = sample_action(F_all, beta, rng)
        F_sa, x_sa = float(F_all[a]), x[a]
        ret, ok = 0.0, False
        for t in range(max_steps):
            pos, r, terminated = env_step(pos, a, right, corridor_length)
            y_next = observation(pos, s0, s1, corridor_length, matching)
            m_next = predictor_step(P, m, y, eye[a], hp)
            s_next = np.concatenate([y_next, m_next])
            F_next, x_next = free_energy_all_actions(s_next, *params)
            a_next = sample_action(F_next, beta, rng)
            delta = td_error(r, F_sa, float(F_next[a_next]), gamma, terminated)
            h_sa = sigmoid(x_sa)
            sarsa_update(params, s, a, h_sa, delta, alpha)
            ret += gamma**t * r
            agent_steps += 1
            F_sa, x_sa = float(F_next[a_next]), x_next[a_next]
            if td_fresh:
                F_sa, x_sa = fresh_pair(s, a, h_sa, delta, alpha, s_next, a_next, F_sa, x_sa)
            y, m, s, a = y_next, m_next, s_next, a_next
            if terminated:
                ok = r > 0
                break
        returns[k], lengths[k], correct[k] = ret, t + 1, ok
    wall = time.perf_counter() - t0
    return {
        "discounted_return": returns,
        "steps": lengths,
        "correct_goal": correct,
        "params": params,
        "agent_steps": agent_steps,
        "wall_time_s": wall,
        "steps_per_s": agent_steps / wall if wall > 0 else float("inf"),
    }


def run_numpy_bptt_reference(sequences, epochs=1, seed=0, lr=0.05, n_memory=20, hp=JOINT) -> dict:
    """Pattern-mode BPTT of one run's joint predictor over ``sequences``, ``epochs`` shuffled epochs."""
    rng = np.random.default_rng(seed)
    P = init_predictor(rng, n_memory=n_memory)
    t0 = time.perf_counter()
    for _ in range(epochs):
        bptt_epoch(P, sequences, rng.permutation(len(sequences)), lr, hp)
    wall = time.perf_counter() - t0
    n = epochs * len(sequences)
    return {"params": P, "wall_time_s": wall, "sequences_per_s": n / wall if wall > 0 else float("inf")}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--sequences", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = run_numpy_tmaze_reference(args.episodes, seed=args.seed)
    last = slice(-max(1, args.episodes // 10), None)
    print(
        f"actor phase: {args.episodes} episodes, {out['agent_steps']} steps, {out['wall_time_s']:.2f} s, "
        f"{out['steps_per_s']:.0f} steps/s; last 10 %: return {out['discounted_return'][last].mean():.3f}, "
        f"correct {out['correct_goal'][last].mean():.2f}"
    )
    seqs = random_sequences(args.sequences, np.random.default_rng(args.seed), lengths=range(3, 8))
    bp = run_numpy_bptt_reference(seqs, seed=args.seed)
    print(f"BPTT: {args.sequences} sequences, {bp['wall_time_s']:.2f} s, {bp['sequences_per_s']:.0f} sequences/s")


if __name__ == "__main__":
    main()
