"""A JAX reference of ferl's recurrent Q-learner on the passive T-maze: the limit that ferl's
compiled path stands beside (docs/performance.md, "Graphs of fixed size"). Optional: it needs
``pip install -e '.[jax]'`` (jax, jaxlib), and nothing in ferl imports JAX.

    python benchmarks/jax_reference.py [--corridors 10 50 200 1000] [--episodes 1000 1000 100 30]
                                       [--runs 10] [--seed 0] [--ferl eager cold]

It is written in the style of PureJaxRL (Lu et al. 2022, "Discovered policy optimisation";
github.com/luchris429/purejaxrl): the environment in JAX, every run's training ``jax.vmap``-ed
(weights (runs, …)), the whole training loop one ``jax.jit`` with ``lax.scan`` over the episodes
and, inside each, over the time steps, the random keys split visibly (``jax.random.split``).

The agent and task are ferl's, at its defaults (docs/beyond.md, "The recurrent Q-learner" and
"The passive T-maze"): ``benchmarks.jobs.PASSIVE_Q`` (``experiment=passive_tmaze
actor=recurrent_q actor.head=linear actor.memory=gru``, conf/actor/recurrent_q.yaml), i.e. DRQN
(Hausknecht & Stone 2015) on Ni et al. (2023)'s passive T-maze (ferl/envs/passive.py) with rewards
× 5: a GRU of 20 units (PyTorch's gates and initialisation U(±1/√H)) over (the 7 observation bits,
the previous action one-hot), a linear Q head; acting by softmax(β Q), β rising linearly 0 → 8.9
over the training; after every episode one Adam step (α 0.0254, Kingma & Ba's β1, β2, ε) on 16
episodes per run drawn uniformly from its last 1 000, unrolled from the zero state by BPTT over the
whole episode, on the mean Huber TD loss against a target network copied every 100 episodes
(ferl/actors/recurrent_q.py). γ = 0.95. `solved` as ferl's (docs/records.md): over the final
window (200 episodes) a correct-goal rate ≥ 0.95 and a discounted return ≥ 0.95 × the optimum.
It need not equal ferl's numbers draw for draw (its random streams are JAX's).

Every L runs in a subprocess of its own (an empty JAX cache: the process's seconds include
Python's start, the imports and compiling). Prints a markdown table: the process's seconds,
compiling (tracing + XLA, ``jit(...).lower(...).compile()``), agent-steps/s of the compiled
training (runs × environment steps ÷ its wall time, compiling excluded), the solved runs and
the final window's mean discounted return; then every run's. ``--ferl MODES`` runs ferl's job at
each L right after the reference's (``bench_chunks.job``: ``eager`` or ``cold``, an empty inductor
cache), so the rows stand side by side. Merges the rows into benchmarks/results.json under
"jax_reference".
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

ROOT = Path(__file__).resolve().parents[1]

N_ACTIONS = 4  # N E S W (ferl/envs/compass.py)
# the 7 observation bits (ferl.envs.tmaze.observation_bits: start, corridor, junction, goal_left,
# goal_right, signal 0, signal 1) of the passive maze's observations, in this order: start_0,
# start_1 (the cue, at the first step only), corridor, junction, goal_left, goal_right
START, CORRIDOR, JUNCTION, GOAL_LEFT, GOAL_RIGHT = 0, 2, 3, 4, 5
OBS_BITS = np.zeros((6, 7), np.float32)
for _obs, _bits in enumerate(((0, 5), (0, 6), (1,), (2,), (3,), (4,))):
    OBS_BITS[_obs, list(_bits)] = 1.0
ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-8


class Config(NamedTuple):
    """ferl's defaults: conf/experiment/passive_tmaze.yaml, conf/actor/recurrent_q.yaml."""

    corridor: int = 10  # Ni et al.'s L; an episode is exactly L + 1 actions
    episodes: int = 1000
    goal_reward: float = 5.0
    n_hidden: int = 20
    gamma: float = 0.95
    lr: float = 0.0254
    beta_end: float = 8.9  # β = beta_end · k / episodes at episode k
    replay_episodes: int = 1000
    batch_episodes: int = 16
    target_every: int = 100
    final_window: int = 200


# --- the passive T-maze (ferl/envs/passive.py): cells 0 … L up the corridor, the junction at L,
# the goals L + 1 (left) and L + 2 (right); cue 1 pays the right goal


def observation(position, t, cue, L: int):
    """The observation's index into OBS_BITS: the cue at the first step only (the start
    revisited looks like the corridor)."""
    at_start = jnp.where(t == 0, START + cue, CORRIDOR)
    cell = jnp.where(position < L, CORRIDOR, jnp.where(position == L, JUNCTION, GOAL_LEFT + position - L - 1))
    return jnp.where(position == 0, at_start, cell)


def env_step(position, t, cue, action, L: int, goal_reward: float):
    """(position, t) after ``action``, and its reward: after the t-th action the goal reward in
    the cued goal at the last (t = L + 1), else −goal_reward / L when behind (cell < t)."""
    junction = position == L
    moved = jnp.stack(
        [
            jnp.where(position < L, position + 1, position),  # N (a goal stays put)
            jnp.where(junction, L + 2, position),  # E: the right goal
            jnp.where((position > 0) & (position <= L), position - 1, position),  # S
            jnp.where(junction, L + 1, position),  # W: the left goal
        ]
    )[action]
    t = t + 1
    last = t >= L + 1
    reward = jnp.where(last, goal_reward * (moved == L + 1 + cue), -goal_reward / L * (moved < t))
    return moved, t, reward


def optimal_return(L: int, gamma: float, goal_reward: float) -> float:
    """The optimum of Σ_t γ^t r_{t+1}: L moves up the corridor, then the cued goal."""
    return goal_reward * gamma**L


def returns(rewards, gamma: float):
    """(Σ_t γ^t r_{t+1}, Σ_t r_{t+1}) over the last axis of ``rewards`` (…, T)."""
    discounts = gamma ** jnp.arange(rewards.shape[-1], dtype=rewards.dtype)
    return (rewards * discounts).sum(-1), rewards.sum(-1)


# --- the recurrent Q-learner (ferl/actors/recurrent_q.py, recurrent_cores.py, q_heads.py)


def init_params(key, n_hidden: int) -> dict:
    """U(−1/√H, 1/√H) for the GRU's W_x (X, 3H), W_h (H, 3H), b_x, b_h (3H) and the head's W_q
    (H, nA), b_q (nA): PyTorch's recurrent-cell initialisation, ferl's."""
    X, H = OBS_BITS.shape[1] + N_ACTIONS, n_hidden
    shapes = {"W_x": (X, 3 * H), "W_h": (H, 3 * H), "b_x": (3 * H,), "b_h": (3 * H,)}
    shapes |= {"W_q": (H, N_ACTIONS), "b_q": (N_ACTIONS,)}
    bound = 1 / np.sqrt(H)
    keys = jax.random.split(key, len(shapes))
    return {n: jax.random.uniform(k, s, minval=-bound, maxval=bound) for k, (n, s) in zip(keys, shapes.items())}


def gru(p: dict, x, h):
    """torch.nn.GRUCell's arithmetic (ferl.predictors.gated.gru_cell), gates (r, z, n)."""
    x_r, x_z, x_n = jnp.split(x @ p["W_x"] + p["b_x"], 3, -1)
    h_r, h_z, h_n = jnp.split(h @ p["W_h"] + p["b_h"], 3, -1)
    r, z = jax.nn.sigmoid(x_r + h_r), jax.nn.sigmoid(x_z + h_z)
    n = jnp.tanh(x_n + r * h_n)
    return n + z * (h - n)


def q_values(p: dict, h):
    return h @ p["W_q"] + p["b_q"]


def play(p: dict, key, beta, cfg: Config):
    """One episode of one run at inverse temperature β: the observations (T+1,), actions (T,),
    rewards (T,) and whether it ended in the cued goal. Actions by inverting softmax(β Q)'s CDF
    at a uniform draw (ferl.actors.softmax.sample_categorical)."""
    L = cfg.corridor
    cue_key, act_key = jax.random.split(key)
    cue = jax.random.randint(cue_key, (), 0, 2)
    uniforms = jax.random.uniform(act_key, (L + 1,))

    def step(carry, u):
        position, t, h, a_prev = carry
        obs = observation(position, t, cue, L)
        h = gru(p, jnp.concatenate([jnp.asarray(OBS_BITS)[obs], a_prev]), h)
        probs = jax.nn.softmax(beta * q_values(p, h))
        a = jnp.minimum((jnp.cumsum(probs) < u).sum(), N_ACTIONS - 1)
        position, t, r = env_step(position, t, cue, a, L, cfg.goal_reward)
        return (position, t, h, jax.nn.one_hot(a, N_ACTIONS)), (obs, a, r)

    start = (jnp.int32(0), jnp.int32(0), jnp.zeros(cfg.n_hidden), jnp.zeros(N_ACTIONS))
    (position, t, _, _), (obs, actions, rewards) = lax.scan(step, start, uniforms)
    obs = jnp.append(obs, observation(position, t, cue, L))
    return obs.astype(jnp.int8), actions.astype(jnp.int8), rewards, position == L + 1 + cue


def huber(x):
    """torch.nn.functional.huber_loss's elementwise term, δ = 1."""
    return jnp.where(jnp.abs(x) < 1, 0.5 * x**2, jnp.abs(x) - 0.5)


def loss(p: dict, p_target: dict, obs, actions, rewards, gamma: float):
    """The mean Huber TD loss of episodes obs (B, T+1), actions, rewards (B, T), online and
    target network unrolled together from the zero state, time-major (``lax.scan`` over t):
    y_t = r_{t+1} + γ max_a Q⁻(h_{t+1}, a), no bootstrap after the last action (every passive
    episode lasts T = L + 1 actions and terminates, so every step is valid)."""
    onehot = jax.nn.one_hot(actions, N_ACTIONS)  # (B, T, nA)
    prev = jnp.concatenate([jnp.zeros_like(onehot[:, :1]), onehot], 1)  # a_{t−1}
    x = jnp.concatenate([jnp.asarray(OBS_BITS)[obs], prev], -1).swapaxes(0, 1)  # (T+1, B, X)

    def step(carry, x_t):
        h, h_target = gru(p, x_t, carry[0]), gru(p_target, x_t, carry[1])
        return (h, h_target), (q_values(p, h), q_values(p_target, h_target))

    zero = jnp.zeros((x.shape[1], p["W_h"].shape[0]))
    _, (q, q_target) = lax.scan(step, (zero, zero), x)  # (T+1, B, nA) each
    T = actions.shape[1]
    bootstrap = (jnp.arange(T) < T - 1)[:, None]
    target = rewards.T + gamma * lax.stop_gradient(q_target[1:].max(-1)) * bootstrap
    q_sa = (q[:T] * onehot.swapaxes(0, 1)).sum(-1)
    return huber(q_sa - target).mean()


def adam(p: dict, m: dict, v: dict, g: dict, k, lr: float):
    """Adam's step k (Kingma & Ba 2015) as ferl writes it (recurrent_q_fast.adam_update)."""
    (b1, b2), tree = ADAM_BETAS, jax.tree_util.tree_map
    m = tree(lambda m, g: b1 * m + (1 - b1) * g, m, g)
    v = tree(lambda v, g: b2 * v + (1 - b2) * g * g, v, g)
    step_size, root = lr / (1 - b1**k), jnp.sqrt(1 - b2**k)
    p = tree(lambda p, m, v: p - step_size * m / (jnp.sqrt(v) / root + ADAM_EPS), p, m, v)
    return p, m, v


def make_train(cfg: Config, runs: int):
    """The jitted training of ``runs`` runs from their keys (runs, key): every run's final
    parameters (each (runs, …)) and per episode (runs, episodes) its discounted and
    undiscounted return and whether it ended in the cued goal."""
    T, K, N = cfg.corridor + 1, cfg.replay_episodes, cfg.episodes

    def train(key):
        key, init_key = jax.random.split(key)
        p = init_params(init_key, cfg.n_hidden)
        zeros = jax.tree_util.tree_map(jnp.zeros_like, p)
        replay = (jnp.zeros((K, T + 1), jnp.int8), jnp.zeros((K, T), jnp.int8), jnp.zeros((K, T)))

        def episode(carry, k):
            p, p_target, m, v, replay, key = carry
            key, play_key, draw_key = jax.random.split(key, 3)
            obs, actions, rewards, correct = play(p, play_key, cfg.beta_end * k / N, cfg)
            replay = tuple(buf.at[k % K].set(x) for buf, x in zip(replay, (obs, actions, rewards)))
            index = jax.random.randint(draw_key, (cfg.batch_episodes,), 0, jnp.minimum(k + 1, K))
            g = jax.grad(loss)(p, p_target, *(buf[index] for buf in replay), cfg.gamma)
            p, m, v = adam(p, m, v, g, (k + 1).astype(jnp.float32), cfg.lr)
            copy = (k + 1) % cfg.target_every == 0
            p_target = jax.tree_util.tree_map(lambda new, old: jnp.where(copy, new, old), p, p_target)
            return (p, p_target, m, v, replay, key), (*returns(rewards, cfg.gamma), correct)

        start = (p, p, zeros, zeros, replay, key)
        (p, *_), metrics = lax.scan(episode, start, jnp.arange(N))
        return p, metrics

    return jax.jit(jax.vmap(train))


def run_job(cfg: Config, runs: int, seed: int) -> dict:
    """Compile (timed) and run one job; its numbers and every run's final window."""
    keys = jax.random.split(jax.random.PRNGKey(seed), runs)
    started = time.perf_counter()
    lowered = make_train(cfg, runs).lower(keys)
    traced = time.perf_counter()
    compiled = lowered.compile()
    compile_done = time.perf_counter()
    params, (discounted, undiscounted, correct) = jax.block_until_ready(compiled(keys))
    run_s = time.perf_counter() - compile_done
    W = min(cfg.final_window, cfg.episodes)
    final = np.asarray(discounted)[:, -W:].mean(1)
    correct_rate = np.asarray(correct)[:, -W:].mean(1)
    optimum = optimal_return(cfg.corridor, cfg.gamma, cfg.goal_reward)
    solved = (final >= 0.95 * optimum) & (correct_rate >= 0.95)
    assert params["W_h"].shape == (runs, cfg.n_hidden, 3 * cfg.n_hidden)
    return {
        "trace_s": traced - started,
        "compile_s": compile_done - started,
        "run_s": run_s,
        "agent_steps_per_s": runs * cfg.episodes * (cfg.corridor + 1) / run_s,
        "solved": int(solved.sum()),
        "optimal_return": optimum,
        "final_discounted_return": final.tolist(),
        "final_return": np.asarray(undiscounted)[:, -W:].mean(1).tolist(),
        "final_correct_goal_rate": correct_rate.tolist(),
    }


def child(corridor: int, episodes: int, runs: int, seed: int) -> None:
    """One job in this process: prints its row as JSON."""
    row = run_job(Config(corridor=corridor, episodes=episodes), runs, seed)
    print(json.dumps(row))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--corridors", type=int, nargs="+", default=[10, 50, 200, 1000])
    parser.add_argument("--episodes", type=int, nargs="+", default=[1000], help="one, or one per corridor")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ferl", nargs="*", choices=["eager", "cold"], default=[], help="ferl's job beside")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if len(args.episodes) not in (1, len(args.corridors)):
        raise SystemExit("jax_reference.py: --episodes takes one number or one per corridor")
    episodes = args.episodes * len(args.corridors) if len(args.episodes) == 1 else args.episodes
    if args.child:
        return child(args.corridors[0], episodes[0], args.runs, args.seed)
    sys.path.insert(0, str(ROOT))
    from benchmarks.bench_chunks import job as ferl_job
    from benchmarks.report import save_results
    from ferl.compiled import EPISODE_CHUNK_STEPS

    rows = []
    print(
        "| impl | L | T_max | episodes | runs | process s | compile s | agent-steps/s | solved | final return | load |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp:
        for corridor, n in zip(args.corridors, episodes):
            command = [sys.executable, __file__, "--child", "--corridors", str(corridor), "--episodes", str(n)]
            started = time.perf_counter()
            done = subprocess.run(
                [*command, "--runs", str(args.runs), "--seed", str(args.seed)], capture_output=True, text=True
            )
            process_s = time.perf_counter() - started
            if done.returncode != 0:
                tail = done.stderr.strip().splitlines()[-1:] or ["no output"]
                raise SystemExit(f"jax_reference.py: L={corridor} failed: {tail[0]}")
            row = {"impl": "jax", "corridor": corridor, "t_max": corridor + 1, "episodes": n, "runs": args.runs}
            row |= {"process_s": process_s, **json.loads(done.stdout.strip().splitlines()[-1])}
            row |= {"final_mean": float(np.mean(row["final_discounted_return"])), "load": os.getloadavg()[0]}
            rows.append(row)
            for mode in args.ferl:  # ferl's job right after, 10 runs as ferl's experiment has them
                out = Path(tmp) / f"ferl_L{corridor}_{mode}"
                f = ferl_job("recurrent_q", corridor, n, mode, EPISODE_CHUNK_STEPS, out, Path(tmp) / f"cache{corridor}")
                rows.append(
                    {
                        "impl": f"ferl {mode}",
                        **f,
                        "runs": 10,
                        "compile_s": f["compile_time_s"],
                        "final_mean": None,
                        "load": os.getloadavg()[0],
                    }
                )
            for r in rows[-1 - len(args.ferl) :]:
                final = "—" if r["final_mean"] is None else f"{r['final_mean']:.3f}"
                print(
                    f"| {r['impl']} | {corridor} | {corridor + 1} | {n} | {r['runs']} | {r['process_s']:.1f} | "
                    f"{r['compile_s']:.1f} | {r['agent_steps_per_s']:.0f} | {r['solved']} | {final} | "
                    f"{r['load']:.2f} |",
                    flush=True,
                )
    for r in rows:
        if r["impl"] == "jax":
            returns_ = " ".join(f"{x:.3f}" for x in r["final_discounted_return"])
            print(f"L={r['corridor']}: final discounted return per run (optimum {r['optimal_return']:.3g}): {returns_}")
    save_results(ROOT / "benchmarks" / "results.json", "jax_reference", "cpu", rows=rows)


if __name__ == "__main__":
    main()
