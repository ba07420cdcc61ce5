"""A supervised upper bound for the large-action task (Sallans & Hinton 2004, JMLR 5:1063–1088, §5):
the reward per step that the FERL actor's product of experts reaches when its parameters are fit
by regression to the exact rewards instead of learnt by TD, and it then chooses by its own Gibbs
selection; docs/beyond.md ("What the variants measured") sets it beside what TD learns. It bounds
what a PoE of H hidden units can earn only as well as the regression is optimised: a fit that
stops early (its RMSE says how far) understates the model, and the key-state construction
(``construct``) shows what the model can represent that a fit from random weights does not find.

The PoE is the actor's RBM, Q(s, a) = −F(s, a) = sᵀb_s + aᵀb_a + Σ_k softplus((W_shᵀs + W_ahᵀa + b_h)_k)
(Eqs. 2.21–2.22, 3.1). Its parameters, run dimension first, are fit by Adam on
Σ_runs mean_batch (Q(s, a) − r(s, a))², Q from the actor's own ``evaluate_actions`` (one formula),
the gradient by autograd. Every step draws a fresh batch: states from the task's own law (uniform,
or the 13 key states for ``env.states=key_states``), actions from a mixture (``draw_actions``):

* ⅓ uniformly random bits (reward ≈ 20 ± 3: what a chain sees early);
* ⅓ the key action of the state's nearest key state, each bit flipped with probability p ~ U(0, ½)
  (rewards 20 … 40: the slope towards the optimum);
* ⅓ the key action of a uniformly drawn key state, flipped likewise (the other key actions'
  basins, where a Gibbs chain may settle).

The rewards are the environment's own (``LargeActionTask.reward``, called on a view of the task
whose runs are run × sample). Then the fitted parameters sit in the experiment's FERLActor
(``conf/experiment/large_action*.yaml``: 100 Gibbs sweeps; β at the end of training, 10), which
chooses by ``gibbs_bits`` (what ``act`` does with 2⁴⁰ actions) in fresh states. For reference
without sampling error: the best fitted Q found by greedy bit-flip ascent (``ascend``) started
from the Gibbs chains' ends and from the 13 key actions — a local search, a lower bound on max_a Q,
so its reward is that of the best action the model is known to rank first, not a proven argmax.

    python baselines/large_action_bound.py [--hidden 13 40 100] [--runs 10] [--out FILE.json]

prints a Markdown table (reward per step mean ± s.e.m. over runs, fit RMSE, wall times).
"""

import argparse
import copy
import json
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from ferl import rng, stats
from ferl.actors.free_energy import FERLActor
from ferl.bits import from_bits, to_bits
from ferl.envs.large_action import LargeActionTask
from ferl.trainers.job import build

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ("large_action", "large_action_key_states")
PARAMETERS = ("W_sh", "W_ah", "b_s", "b_a", "b_h")  # the FERLActor's, each (R, …)
CHUNK = 256  # samples per run handled at once where memory grows with them (rewards, Gibbs chains)


def experiment(name: str, n_hidden: int, n_runs: int, seed: int = 0):
    """The task (R runs, each its run's task of ``train.py experiment=name seed=seed``), the
    experiment's actor with ``n_hidden`` hidden units, and β at the end of its schedule."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(
            "config", [f"experiment={name}", f"actor.n_hidden={n_hidden}", f"n_runs={n_runs}", f"seed={seed}"]
        )
    offsets = rng.NAMED_OFFSETS[cfg.trainer.seed_offsets]  # what the trainer's Job adds (ferl.trainers.job)
    task = build(cfg.env, n_runs=n_runs, generator=rng.generator(seed), seed=seed + offsets.env)
    actor = build(
        cfg.actor,
        "actor.",
        n_runs=n_runs,
        n_state=task.observation_size,
        n_actions=task.n_actions,
        seed=seed + offsets.actor,
    )
    return task, actor, float(instantiate(cfg.actor.beta)(1.0))


def per_sample(task: LargeActionTask, n: int) -> LargeActionTask:
    """A view of the task whose runs are (run, sample) pairs, R·n of them, run-major."""
    view = copy.copy(task)
    view.keys, view.key_actions = (t.repeat_interleave(n, 0) for t in (task.keys, task.key_actions))
    view.n_runs = task.n_runs * n
    return view


def rewards(task: LargeActionTask, s: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
    """The environment's own rewards of B (state, action) pairs per run: s (R, B, S), action bits
    (R, B, K) → (R, B), ``CHUNK`` pairs per run at a time."""
    parts = []
    for s_c, a_c in zip(s.split(CHUNK, 1), bits.split(CHUNK, 1)):
        view = per_sample(task, s_c.shape[1])
        parts.append(view.reward(s_c.flatten(0, 1), from_bits(a_c.flatten(0, 1))).view(s_c.shape[:2]))
    return torch.cat(parts, 1)


def states(task: LargeActionTask, n: int) -> torch.Tensor:
    """The next n states of the task's own stream, (R, n, S)."""
    return task.step_inputs(n)[0].transpose(0, 1).contiguous()


def nearest_keys(task: LargeActionTask, s: torch.Tensor) -> torch.Tensor:
    """The task's nearest key state (its own rule, ties to the lower index) of s (R, B, S) → (R, B)."""
    return per_sample(task, s.shape[1]).nearest_key(s.flatten(0, 1)).view(s.shape[:2])


def draw_actions(task: LargeActionTask, s: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Action bits (R, B, K) from the fit's mixture (module docstring): ⅓ uniform, ⅓ near the
    nearest key state's key action, ⅓ near a random key state's key action."""
    R, B, _ = s.shape
    n_keys, K = task.key_actions.shape[1:]
    component = torch.randint(3, (R, B), generator=generator)
    key = torch.where(component == 1, nearest_keys(task, s), torch.randint(n_keys, (R, B), generator=generator))
    centre = task.key_actions[torch.arange(R).unsqueeze(1), key]  # (R, B, K)
    flip_rate = torch.where(component == 0, 0.5, 0.5 * torch.rand(R, B, generator=generator)).unsqueeze(-1)
    flips = torch.rand(R, B, K, generator=generator) < flip_rate
    return torch.where(flips, 1 - centre, centre)


def q_values(actor: FERLActor, s: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
    """Q = −F (R, B) of the actor's RBM at s (R, B, S) and action bits (R, B, K) (Eq. 3.1)."""
    return -actor.evaluate_actions(s, from_bits(bits))[0]


def construct(actor: FERLActor, task: LargeActionTask, gain: float, margin: float) -> FERLActor:
    """Set hidden unit j < 13 of every run to the key-state expert of key state k_j with key action c_j,
    in place: x_j = gain (sᵀ(2k_j − 1) − |k_j| + margin) + aᵀ(2c_j − 1) + |1 − c_j|. Since
    sᵀ(2k_j − 1) − |k_j| = −d(s, k_j) (Hamming distance), x_j is the reward of a when s is within
    ``margin`` of k_j and far below 0 elsewhere (gain large), so Q = Σ_j softplus(x_j) is
    softplus(r(s, a)) = r + ln(1 + e^(−r)) wherever s lies within ``margin`` of one key state only:
    at the key states of ``env.states=key_states`` (margin 0, distinct keys) Q is the reward up to
    e^(−r) — 13 hidden units represent that task. Hidden units beyond 13 keep their weights and are
    switched off (b_h = −gain), visible biases zeroed. A start for ``fit``."""
    n = min(actor.n_hidden, task.keys.shape[1])
    keys, key_actions = task.keys[:, :n], task.key_actions[:, :n]  # (R, n, S), (R, n, K)
    actor.W_sh[:, :, :n] = gain * (2 * keys - 1).transpose(1, 2)
    actor.W_ah[:, :, :n] = (2 * key_actions - 1).transpose(1, 2)
    actor.b_h[:, :n] = gain * (margin - keys.sum(-1)) + (1 - key_actions).sum(-1)
    actor.b_h[:, n:] = -gain
    actor.b_s.zero_()
    actor.b_a.zero_()
    return actor


def fit(
    actor: FERLActor, task: LargeActionTask, steps: int, batch: int, lr: float, generator: torch.Generator
) -> FERLActor:
    """Fit the actor's parameters in place by Adam on Σ_runs mean (Q − r)² over fresh batches of
    ``batch`` pairs per run; α decays from ``lr`` to lr / 100 exponentially. Adam's moments are elementwise, so each run's parameters move by their
    own run's errors only."""
    params = [getattr(actor, name).clone().requires_grad_() for name in PARAMETERS]
    for name, p in zip(PARAMETERS, params):
        setattr(actor, name, p)  # buffers that autograd tracks through evaluate_actions
    opt = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=0.01 ** (1 / max(1, steps)))
    for _ in range(steps):
        s = states(task, batch)
        bits = draw_actions(task, s, generator)
        loss = (q_values(actor, s, bits) - rewards(task, s, bits)).pow(2).mean(1).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    for name, p in zip(PARAMETERS, params):
        setattr(actor, name, p.detach())
    return actor


@torch.no_grad()
def rmse(actor: FERLActor, task: LargeActionTask, n: int, generator: torch.Generator) -> torch.Tensor:
    """Root mean squared error (R,) of Q against the reward on n fresh pairs per run of the fit's law."""
    s = states(task, n)
    bits = draw_actions(task, s, generator)
    return (q_values(actor, s, bits) - rewards(task, s, bits)).pow(2).mean(1).sqrt()


@torch.no_grad()
def gibbs_choices(actor: FERLActor, s: torch.Tensor, beta: float, generator: torch.Generator) -> torch.Tensor:
    """The action bits (R, B, K) that the actor's Gibbs selection (``gibbs_bits``) picks at s (R, B, S)."""
    picks = [
        actor.gibbs_bits(s_c, beta, actor.chain_uniforms(s_c, generator, None, factored=True))
        for s_c in s.split(CHUNK, 1)
    ]
    return to_bits(torch.cat(picks, 1), actor.W_ah.shape[1]).to(actor.W_ah.dtype)


@torch.no_grad()
def ascend(actor: FERLActor, s: torch.Tensor, bits: torch.Tensor, max_rounds: int = 200) -> torch.Tensor:
    """Greedy bit-flip ascent of Q from action bits (R, B, K) at s (R, B, S): each round flips, in
    every pair, the bit whose flip raises Q most, until no flip raises it. Flipping bit k moves the
    hidden input x by d_k W_ah[k] (d_k = 1 − 2 a_k) and Q by κ (d_k b_a,k + Σ_j φ(x_j + d_k W_ah[k, j]) − φ(x_j))."""
    bits = bits.clone()
    x_s = torch.baddbmm(actor.b_h.unsqueeze(1), s, actor.W_sh)
    phi = actor.form.hidden_term
    for _ in range(max_rounds):
        x = torch.baddbmm(x_s, bits, actor.W_ah)  # (R, B, H)
        d = 1 - 2 * bits  # (R, B, K)
        moved = x.unsqueeze(2) + d.unsqueeze(-1) * actor.W_ah.unsqueeze(1)  # (R, B, K, H)
        gain = actor.scaled(d * actor.b_a.unsqueeze(1) + (phi(moved) - phi(x).unsqueeze(2)).sum(-1))
        best, k = gain.max(-1)
        up = best > 1e-6
        if not up.any():
            break
        flip = torch.nn.functional.one_hot(k, bits.shape[-1]).to(bits.dtype) * up.unsqueeze(-1)
        bits = (bits + flip * d).abs()
    return bits


@torch.no_grad()
def best_found(actor: FERLActor, task: LargeActionTask, s: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
    """The highest-Q local optimum (R, B, K) of ``ascend`` from each of C starts (R, B, C, K) and
    from the task's key actions, ``CHUNK`` states at a time."""
    R, B, _, K = starts.shape
    keys = task.key_actions.unsqueeze(1).expand(R, B, -1, K)
    starts = torch.cat([starts, keys], 2)
    out = []
    for s_c, st_c in zip(s.split(CHUNK // 8, 1), starts.split(CHUNK // 8, 1)):
        n = st_c.shape[2]
        s_rep = s_c.unsqueeze(2).expand(-1, -1, n, -1).flatten(1, 2)
        found = ascend(actor, s_rep, st_c.flatten(1, 2))
        q = q_values(actor, s_rep, found).view(R, -1, n)
        out.append(found.view(R, -1, n, K)[torch.arange(R)[:, None], torch.arange(q.shape[1])[None], q.argmax(-1)])
    return torch.cat(out, 1)


def measure(name: str, n_hidden: int, args) -> dict:
    """Fit, then Gibbs selection and local search in ``args.states`` fresh states: per-run numbers."""
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(args.seed)
    task, actor, beta = experiment(name, n_hidden, args.runs, args.seed)
    if args.init == "keys":
        construct(actor, task, gain=60.0, margin=0.0)
    started = time.perf_counter()
    fit(actor, task, args.fit_steps, args.batch, args.lr, generator)
    fit_s = time.perf_counter() - started
    error = rmse(actor, task, 4096, generator)
    started = time.perf_counter()
    s = states(task, args.states)
    chains = torch.stack([gibbs_choices(actor, s, beta, generator) for _ in range(args.chains)], 2)  # (R, B, C, K)
    gibbs = rewards(task, s, chains[:, :, 0])
    gibbs_s = time.perf_counter() - started
    started = time.perf_counter()
    found = best_found(actor, task, s[:, : args.search_states], chains[:, : args.search_states])
    search = rewards(task, s[:, : args.search_states], found)
    search_s = time.perf_counter() - started
    return {
        "experiment": name,
        "n_hidden": n_hidden,
        "init": args.init,
        "fit_steps": args.fit_steps,
        "beta": beta,
        "gibbs_sweeps": actor.gibbs_sweeps,
        "rmse": error.tolist(),
        "gibbs_reward": gibbs.mean(1).tolist(),
        "search_reward": search.mean(1).tolist(),
        "fit_s": fit_s,
        "gibbs_s": gibbs_s,
        "search_s": search_s,
    }


def mean_sem(values: list[float]) -> str:
    """mean ± s.e.m. over the runs (``ferl.stats.mean_sem``), to one decimal."""
    mean, sem, _ = stats.mean_sem(values)
    return f"{mean:.1f} ± {sem:.1f}"


def table(rows: list[dict]) -> str:
    """The Markdown table of ``measure``'s rows."""
    lines = [
        "| task | H | start, Adam steps | Gibbs selection (reward/step) | best Q found (local search) | fit RMSE | fit / Gibbs / search s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| `{r['experiment']}` | {r['n_hidden']} | {r['init']}, {r['fit_steps']} | {mean_sem(r['gibbs_reward'])} | {mean_sem(r['search_reward'])} "
            f"| {mean_sem(r['rmse'])} | {r['fit_s']:.0f} / {r['gibbs_s']:.0f} / {r['search_s']:.0f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--experiments", nargs="+", default=list(EXPERIMENTS), choices=EXPERIMENTS)
    p.add_argument("--hidden", nargs="+", type=int, default=[13, 40, 100])
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--init",
        choices=("actor", "keys"),
        default="actor",
        help="the fit's start: the actor's random weights, or the key-state experts (construct)",
    )
    p.add_argument("--fit-steps", type=int, default=2000)
    p.add_argument("--batch", type=int, default=512, help="pairs per run per Adam step")
    p.add_argument("--lr", type=float, default=0.03)
    p.add_argument("--states", type=int, default=1000, help="fresh states per run for Gibbs selection")
    p.add_argument("--chains", type=int, default=2, help="Gibbs chains per state (the first is the reward)")
    p.add_argument("--search-states", type=int, default=300, help="of those, states for the local search")
    p.add_argument("--out", type=Path, help="JSON file of every run's numbers")
    args = p.parse_args(argv)
    for key in ("runs", "fit_steps", "batch", "states", "chains", "search_states"):
        if getattr(args, key) < 1:
            raise SystemExit(f"large_action_bound.py: --{key.replace('_', '-')} must be at least 1")
    if min(args.hidden) < 1 or args.search_states > args.states or args.lr <= 0:
        raise SystemExit("large_action_bound.py: needs --hidden ≥ 1, --search-states ≤ --states and --lr > 0")
    torch.set_num_threads(1)
    rows = []
    for name in args.experiments:
        for h in args.hidden:
            rows.append(measure(name, h, args))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    print(table(rows))
    if args.out:
        args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
