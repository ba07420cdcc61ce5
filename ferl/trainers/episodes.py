"""Episode data for the predictors (§4.3.1 "Training procedure", Algorithm 1).

N_sample random-policy episodes per run are collected, balanced to an equal number of
episodes per step-length T = T_min … T_max, and split 80 / 20 into training and test data.
Only lengths T_min … T_min + L_training − 1 are trained on; the longer ones measure how the
predictor generalises (Fig. 4.5, right-hand columns).

Episodes are stored padded: obs (R, N, T_max+1) observation ids, actions (R, N, T_max),
rewards (R, N, T_max), lengths (R, N) — the same N for every run, so training batches over runs.
An id stands for the (processed) observation in ``ObservationTable``.
"""

from typing import NamedTuple

import torch
import torch.nn.functional as F

from ferl.config.params import ConfigError
from ferl.trainers.handoffs import Episodes  # also the name older checkpoints unpickle it by


@torch.no_grad()
def collect_random_episodes(env, n_episodes_per_run: int, n_runs: int, generator) -> Episodes:
    """Random-policy episodes from ``env``, a T-maze batched over n_runs × k copies: every
    reset starts k episodes of each run at once. Returns n_episodes_per_run per run."""
    copies = env.n_runs // n_runs
    rounds = -(-n_episodes_per_run // copies)
    T = env.max_steps
    chunks = []
    for _ in range(rounds):
        env.reset()
        obs = torch.full((env.n_runs, T + 1), -1, dtype=torch.long, device=env.device)
        actions = torch.zeros(env.n_runs, T, dtype=torch.long, device=env.device)
        rewards = torch.zeros(env.n_runs, T, device=env.device)
        obs[:, 0] = env.obs_id
        for t in range(T):
            a = torch.randint(env.n_actions, (env.n_runs,), generator=generator, device=env.device)
            active = ~env.done
            _, r, _, _ = env.step(a)
            actions[:, t] = torch.where(active, a, 0)
            rewards[:, t] = r
            obs[:, t + 1] = torch.where(active, env.obs_id, -1)
        chunks.append((obs, actions, rewards, env.t.clone()))
    stack = [
        torch.stack([c[i] for c in chunks], 1).view(n_runs, copies * rounds, *chunks[0][i].shape[1:]) for i in range(4)
    ]
    episodes = Episodes(*stack)
    keep = torch.arange(n_episodes_per_run, device=env.device).expand(n_runs, -1)
    return episodes.select(keep)


def balance_and_split(episodes: Episodes, t_min: int, t_max: int, train_fraction: float, generator):
    """Equal numbers of episodes per step-length and an 80/20 split within every length.

    n per length = the smallest count of any length T_min … T_max in any run, so every run
    keeps the same number (padded batching over runs needs it). Returns (train, test) Episodes,
    each ordered by length, and the per-length counts (n_train, n_test).
    """
    lengths = episodes.lengths
    R, N = lengths.shape
    counts = torch.stack([(lengths == T).sum(1) for T in range(t_min, t_max + 1)])  # (nT, R)
    n = int(counts.min())
    if n < 2:
        raise ConfigError(
            f"trainer.n_sample: too few random episodes of some length in [{t_min}, {t_max}] "
            f"to balance (smallest count {n}); collect more"
        )
    n_train = max(1, round(train_fraction * n))
    train_idx, test_idx = [], []
    for T in range(t_min, t_max + 1):
        # random keys, −inf for other lengths: the n largest are n random episodes of length T
        keys = torch.rand(R, N, generator=generator, device=lengths.device).masked_fill(lengths != T, -1.0)
        pick = keys.topk(n, dim=1).indices
        train_idx.append(pick[:, :n_train])
        test_idx.append(pick[:, n_train:])
    return (episodes.select(torch.cat(train_idx, 1)), episodes.select(torch.cat(test_idx, 1)), (n_train, n - n_train))


class ObservationTable:
    """The (processed) observation of every observation id: the environment's table (ids, Y),
    shared by every run, or once a preprocessor has processed it, one per run (R, ids, Y)."""

    def __init__(self, table: torch.Tensor):
        self.table = table

    @property
    def per_run(self) -> bool:
        return self.table.dim() == 3

    def lookup(self, ids: torch.Tensor) -> torch.Tensor:
        """Observation vectors of valid ids (R, …) → (R, …, Y)."""
        if not self.per_run:
            return self.table[ids]
        runs = torch.arange(self.table.shape[0], device=ids.device).view(-1, *([1] * (ids.dim() - 1)))
        return self.table[runs, ids]

    def observations(self, ids: torch.Tensor) -> torch.Tensor:
        """As ``lookup`` for padded episodes: the padding id −1 gives zeros."""
        return torch.where((ids >= 0).unsqueeze(-1), self.lookup(ids.clamp(min=0)), 0.0)


def episode_bytes(t_max: int) -> int:
    """Bytes of one padded episode of ``Episodes``."""
    return 8 * (t_max + 1) + 8 * t_max + 4 * t_max + 8


def observation_table(job) -> ObservationTable:
    """The observations the predictors and the actor see: processed where a phase stored them."""
    processed = job.outputs.observations
    return ObservationTable(processed if processed is not None else job.env.observation_table)


def episode_tensors(job, ep: Episodes, predictor):
    """Episodes → predictor inputs y (R,B,T+1,Y), a (R,B,T,A), the reward targets (R,B,T+1,·) of
    ``predictor`` (None without one or without a reward output), lengths."""
    y = observation_table(job).observations(ep.obs)
    a = F.one_hot(ep.actions, job.env.n_actions).float()
    r = predictor.reward_targets(job.env.reward_values, ep.rewards) if predictor is not None else None
    return y, a, r, ep.lengths


def discount_factors(gamma: float, t_max: int) -> list[float]:
    """γ^0 … γ^(t_max − 1) as Python floats (float64), each the product of the one before and γ:
    IEEE multiplications in a fixed order, the same numbers on every CPU (a vectorised ``pow``
    may round differently where it runs other kernels)."""
    factors = [1.0]
    for _ in range(t_max - 1):
        factors.append(factors[-1] * gamma)
    return factors[:t_max]


def discounted_return(discounts: list[float], rewards: torch.Tensor) -> torch.Tensor:
    """R_0^γ = Σ_t γ^t r_(t+1) (Eq. 2.37) of each run, (R,) float32, from the rewards
    (steps, R) and the discounts γ^t (``discount_factors``): accumulated in float64, step by step
    (``returned``), as an episode's steps accumulate it (``ActorEpisodes.steps``)."""
    total = torch.zeros(rewards.shape[1:], dtype=torch.float64, device=rewards.device)
    for t in range(len(rewards)):
        total = returned(total, discounts[t], rewards[t])
    return total.float()


def returned(total: torch.Tensor, discount, reward: torch.Tensor) -> torch.Tensor:
    """The return so far (R,) float64 after one more reward (R,) at discount γ^t: a float64 sum in
    a fixed order, so the recorded metric is the same on every CPU. A float32 product
    ``discounts @ rewards`` sums in the order its BLAS kernel chooses, which differs between CPUs
    (AVX2 or AVX-512, Intel or AMD) in the ninth digit (docs/reliability.md, "Determinism across
    machines")."""
    return total + discount * reward.double()


class Carry(NamedTuple):
    """What an episode of every run carries from one step to the next (``ActorEpisodes.steps``; a
    NamedTuple, so that it crosses from one compiled chunk of steps to the next)."""

    m: list  # every predictor's state m_t (Eq. 4.3)
    memories: list  # every predictor's memory, read from m_t, (R, M) each
    s: torch.Tensor  # (R, 1, S) the actor's state s_t
    a: torch.Tensor  # (R, 1) the action a_t chosen at s_t
    F_sa: torch.Tensor  # (R, 1) F(s_t, a_t)
    x_sa: torch.Tensor  # (R, 1, ·) the actor's cache of (s_t, a_t)
    terminated: torch.Tensor  # (R,) bool: the run's episode ended in a terminal state
    discounted_return: torch.Tensor  # (R,) float64: Σ_t γ^t r_(t+1) so far (Eq. 2.37)


class Step(NamedTuple):
    """One step of an episode of every run, as ``ActorEpisodes.steps`` keeps it (a NamedTuple, so
    that it traces under torch.compile in the fused episode); ``stacked`` over the steps, each field
    gains a leading step axis."""

    probe: torch.Tensor  # (R,) bool: at a probe state, the run's episode on
    active: torch.Tensor  # (R,) bool: the run's episode on
    memories: tuple  # every predictor's memory m_t, (R, M) each
    state: torch.Tensor  # (R, S) the actor's state s_t
    cache: torch.Tensor  # (R, ·) the actor's cache of (s_t, a_t)
    action: torch.Tensor  # (R,) a_t
    reward: torch.Tensor  # (R,) the raw reward r_(t+1)
    delta: torch.Tensor  # (R,) the TD error δ_t


def stacked(steps: list[Step]) -> Step:
    """The steps of an episode as one ``Step`` whose fields are stacked over the steps (steps, R, …).
    Built by ``Step(*fields)``: torch 2.8's dynamo refuses to trace ``Step._make``."""
    fields: list = [
        tuple(torch.stack(m) for m in zip(*field)) if isinstance(field[0], tuple) else torch.stack(field)
        for field in zip(*steps)
    ]
    return Step(*fields)


def played(env, carry: Carry, ep: Step, obs: torch.Tensor) -> dict:
    """What an episode's ``ActorEpisodes.steps`` played in ``env`` (``ep``, (steps, R, …); the
    observation ids ``obs`` (steps + 1, R); the ``carry`` after the last step), as the phase keeps
    it: per step, stacked (steps, R, …), probe and active masks, each predictor's memory, the
    state and the cache of (s, a) at the visit, action, raw reward, δ, observation ids; the last
    state, whether each run's episode terminated, and the outcome (len(outcome_names), R)."""
    steps = env.t
    outcome = torch.stack(
        [  # in the order of outcome_names
            carry.discounted_return.float(),
            steps.float(),
            ep.reward.gather(0, (steps - 1).unsqueeze(0)).squeeze(0),  # terminal reward
            ep.delta.abs().sum(0) / steps.clamp(min=1),
            *(v.float() for v in env.outcomes().values()),
        ]
    )
    return {
        "probes": ep.probe,
        "actives": ep.active,
        "memories": ep.memories,
        "states": ep.state,
        "caches": ep.cache,
        "actions": ep.action,
        "rewards": ep.reward,
        "deltas": ep.delta,
        "obs": obs,
        "last_state": carry.s,
        "terminated": carry.terminated,
        "outcome": outcome,
        "lengths": steps,
    }
