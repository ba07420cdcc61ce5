"""Directed exploration (``ferl.exploration``, config group ``exploration``): εz-greedy's durations
and choices against Dabney et al. (2021)'s Algorithm 1 written out per run, the count bonus against
counts kept in NumPy, and a corridor that εz-greedy crosses where Boltzmann exploration at β = 0
does not. That ``exploration=none`` leaves every number as it was is tests/test_golden.py's."""

import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import open_dict

from conftest import compose_config
from ferl.exploration.counts import CountBonus
from ferl.exploration.ez_greedy import EzGreedy, zeta_cdf, zeta_durations

ZETA = {2.0: math.pi**2 / 6, 3.0: 1.2020569031595942}  # ζ(2) and Apéry's constant ζ(3)


@pytest.mark.parametrize("mu", ZETA)
def test_zeta_durations_have_the_zeta_law_censored_at_the_episode(mu):
    """200 000 durations n ≥ 1, censored at L = 12: frequencies of n = 1 … 11 against n^(−μ)/ζ(μ)
    with ζ in closed form, the last class against the tail 1 − Σ; a chi-square test at 11 degrees
    of freedom (its 0.999 quantile is 31.3)."""
    L, n = 12, 200_000
    u = torch.rand(n, generator=torch.Generator().manual_seed(1))
    durations = zeta_durations(zeta_cdf(mu, L), u).numpy()
    assert durations.min() >= 1 and durations.max() <= L
    k = np.arange(1, L)
    p = np.append(k ** (-mu) / ZETA[mu], 1 - (k ** (-mu)).sum() / ZETA[mu])
    observed = np.bincount(durations, minlength=L + 1)[1:]
    chi2 = ((observed - n * p) ** 2 / (n * p)).sum()
    assert chi2 < 31.3, (observed, n * p)


class TableActor:
    """A stand-in actor: F(s, a) = s · W[:, a] of one run's table, SARSA."""

    td_rule, learns_from_episodes = "sarsa", False

    def __init__(self, W):
        self.W = W  # (R, S, nA)

    def evaluate(self, s):
        F = torch.bmm(s, self.W)
        return F, F.unsqueeze(-1)


@pytest.mark.parametrize(
    ("epsilon", "epsilon_end", "over", "progress"),
    [(0.3, None, 1.0, 0.7), (0.6, 0.0, 1.0, 0.5), (0.6, 0.0, 0.5, 0.25), (0.7, 0.3, 0.5, 0.8)],
)
def test_ez_greedy_follows_algorithm_1_and_evaluates_the_action_taken(epsilon, epsilon_end, over, progress):
    """Per run and step, Algorithm 1 of Dabney et al. written out in Python on the same uniforms:
    an option runs on, else one starts with chance ε (ω and n from the step's uniforms), else the
    actor's proposal; F and the cache returned are the actor's at the action taken. ε is 0.3 in
    every case: constant; 0.6 falling linearly to 0, half-way through the training; the same fall
    over the first half (``epsilon_over``), a quarter through; 0.7 → 0.3 over the first half, held
    at 0.3 after it."""
    R, S, nA, T = 6, 3, 4, 40
    g = torch.Generator().manual_seed(3)
    actor = TableActor(torch.randn(R, S, nA, generator=g))
    explore = EzGreedy(n_runs=R, n_actions=nA, epsilon=epsilon, mu=2.0, epsilon_end=epsilon_end, epsilon_over=over)
    explore.begin_episode(torch.Generator().manual_seed(4), T - 1, progress)
    uniforms = explore.uniforms.clone()  # (T, R, 3)
    cdf = zeta_cdf(2.0, T).numpy()
    held, left = [0] * R, [0] * R
    for t in range(T):
        s = torch.randn(R, 1, S, generator=g)
        proposal_a = torch.randint(nA, (R, 1), generator=g)
        F, _ = actor.evaluate(s)
        proposal = (proposal_a, F.gather(2, proposal_a.unsqueeze(2)).squeeze(2), None, None)
        a, F_a, cache_a, F_boot = explore.choose(actor, s, proposal)
        for r in range(R):
            u_start, u_omega, u_n = uniforms[t, r].tolist()
            if left[r] == 0 and u_start < 0.3:
                held[r], left[r] = int(u_omega * nA), 1 + int((cdf <= u_n).sum())
            want = held[r] if left[r] > 0 else int(proposal_a[r, 0])
            left[r] = max(left[r] - 1, 0)
            assert int(a[r, 0]) == want, (t, r)
        torch.testing.assert_close(F_a, F.gather(2, a.unsqueeze(2)).squeeze(2))
        torch.testing.assert_close(cache_a, F_a.unsqueeze(-1))
        torch.testing.assert_close(F_boot, F_a)  # SARSA bootstraps from the action taken


def test_count_bonus_against_counts_kept_in_numpy():
    """b = scale / sqrt(N(φ(s'))) with φ the sign bits of s' A (A drawn per run from seed + r) and N
    counted per run over the visits so far, this one included; inactive runs count nothing, get 0."""
    R, S, bits, scale, T = 3, 5, 3, 0.5, 30
    bonus = CountBonus(n_runs=R, n_state=S, seed=7, scale=scale, bits=bits)
    A = np.stack([torch.randn(S, bits, generator=torch.Generator().manual_seed(7 + r)).numpy() for r in range(R)])
    counts = np.zeros((R, 2**bits))
    g = torch.Generator().manual_seed(0)
    for _ in range(T):
        s = torch.randn(R, 1, S, generator=g)
        active = torch.rand(R, generator=g) < 0.8
        got = bonus.reward_bonus(s, active).numpy()
        codes = ((np.einsum("rs,rsb->rb", s[:, 0].numpy(), A) > 0) * 2 ** np.arange(bits)).sum(1)
        want = np.zeros(R)
        for r in range(R):
            if active[r]:
                counts[r, codes[r]] += 1
                want[r] = scale / np.sqrt(counts[r, codes[r]])
        np.testing.assert_allclose(got, want, rtol=1e-6)
    np.testing.assert_array_equal(bonus.counts.numpy(), counts)


def actor_phase(*overrides):
    """Algorithm 1's actor phase on the composed config, set up on its job and ready to play."""
    cfg = compose_config(["experiment=table4_1_regular", "predictor=none", *overrides])
    with open_dict(cfg):
        del cfg["hydra"]
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, torch.device("cpu"))
    job, phase = trainer.job, trainer.phases[-1]
    phase.prepare(job)
    phase.freeze(job)
    return job, phase


def goal_share(*exploration: str, episodes: int = 20) -> float:
    """The share of episodes that reach a goal (|terminal reward| = 5) at β = 0 — the online
    trainer's start: undirected Boltzmann exploration — with the actor learning, 16 runs, corridor
    10, T_max 22."""
    job, phase = actor_phase("n_runs=16", "env.corridor_length=10", "env.max_steps=22", *exploration)
    reached = [
        (phase.play_episode(job, k, job.actor.learning_rate(0.0), 0.0)["outcome"][2].abs() == 5).float().mean()
        for k in range(episodes)
    ]
    return float(torch.stack(reached).mean())


def test_ez_greedy_reaches_the_junction_where_boltzmann_does_not():
    """A corridor of 10 in 22 steps: a random walk of N/S moves among wall bumps almost never gets
    there (diffusive: ~T_min² steps), εz-greedy's held actions do (~5 % of the episodes; 0.2 % without,
    measured over 30 episodes), in the same 20 episodes × 16 runs."""
    boltzmann = goal_share("exploration=none")
    directed = goal_share("exploration=ez_greedy", "exploration.epsilon=0.5")
    assert boltzmann <= 0.01 and directed >= 0.025, (boltzmann, directed)


def test_exploration_is_checkpointed_and_named_in_run_json():
    job, _ = actor_phase("n_runs=2", "exploration=count_bonus")
    assert "exploration" in job.components()
    job.exploration.counts[0, 3] = 2.0
    saved = {k: v.clone() for k, v in job.exploration.state_dict().items()}
    job.exploration.counts.zero_()
    job.exploration.load_state_dict(saved)
    assert job.exploration.counts[0, 3] == 2.0
    assert job.describe()["exploration"]["kind"] == "count_bonus"
    none, _ = actor_phase("n_runs=2")
    assert "exploration" not in none.components() and "exploration" not in none.describe()  # as before


def test_ez_greedy_tells_the_recurrent_q_learner_the_action_it_took():
    """The recurrent Q-learner steps its memory in ``act`` with the action it drew; under εz-greedy
    (ε = 0.6: most steps overridden) the memory must read the action taken. Independent check: Q at
    every step of a played episode against the actor's own ``unroll`` (the replay's form, from the
    zero state) over the states and the actions taken; F returned by ``choose`` is −Q of the taken
    action there."""
    from ferl.actors.recurrent_q import RecurrentQActor
    from ferl.schedules import Constant

    R, S, nA, T = 4, 3, 4, 12
    actor = RecurrentQActor(
        n_runs=R, n_state=S, n_actions=nA, n_hidden=5, gamma=0.9, lr=Constant(0.1), beta=Constant(1.0), seed=2
    )
    explore = EzGreedy(n_runs=R, n_actions=nA, epsilon=0.6, mu=2.0)
    explore.begin_episode(torch.Generator().manual_seed(5), T - 1, 0.0)
    g = torch.Generator().manual_seed(6)
    states = torch.randn(R, 1, T, S, generator=g)
    taken_actions, F_taken, overridden = [], [], 0
    for t in range(T):
        proposal = actor.act(states[:, :, t], 1.0, g)
        a, F_a, _, _ = explore.choose(actor, states[:, :, t], proposal)
        overridden += int((a != proposal[0]).sum())
        taken_actions.append(a)
        F_taken.append(F_a)
    actions = torch.cat(taken_actions, 1).unsqueeze(1)  # (R, 1, T)
    onehot = torch.nn.functional.one_hot(actions, nA).float()
    prev = torch.cat([torch.zeros_like(onehot[:, :, :1]), onehot[:, :, :-1]], 2)  # a_{t−1}, zero at t = 0
    q = actor.unroll(actor.params(), states, prev)  # (R, 1, T, nA)
    want = -q.gather(3, actions.unsqueeze(3)).squeeze(3).squeeze(1)  # (R, T)
    assert overridden > 0
    torch.testing.assert_close(torch.cat(F_taken, 1), want)
