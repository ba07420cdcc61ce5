"""Online training (§5.4): predictors and actor learn together from the first episode.

§5.4 proposes to "mix the training phase of a predictor and an actor": instead of Algorithm 1/2's
random collection → predictor training → actor training, the agent acts on its predictors' current
memory from its first episode, and after every episode

* the episode goes into a replay of each run's last K episodes (``replay_episodes``), and every
  predictor takes BPTT steps (its own ``lr`` and objective, §4.3.1) on ``replay_sample`` episodes
  drawn uniformly from it, one step on the summed loss of every ``replay_batch_size`` of them
  (the first-order sum of as many pattern-mode steps at its ``lr``; its own ``batch_size`` when
  null);
* a predictor that normalises its scalar reward (``reward_norm=popart``, ``ferl.predictors.popart``)
  merges the episode's rewards into its statistics, once;
* its prediction error e_k (Eq. 4.8 per step, mean over the episode's steps, summed over the
  predictors) is measured *before* the predictors train on it — a held-out error — and tracked as
  ē_k = (1 − λ) ē_{k−1} + λ e_k (``error_ema`` λ; ē_0 = e_0).

The inverse temperature follows the predictor (§5.4: "When the predictor's performance is not
satisfactory, an actor can explore … with a low inverse temperature β"), per run:

    β_k = β_actor(k / N) · clip((1 − ē_k / e_0) / (1 − τ), 0, 1)

with β_actor the actor's own schedule, e_0 the untrained predictor's error of the first episode and
τ = ``beta_error_ratio``: β stays 0 (random actions, as Algorithm 1's collection) until the error
falls, and reaches the actor's schedule once ē_k ≤ τ e_0.

Curiosity (§5.4: "Prediction errors can also be added to the raw reward to boost exploration"):
the actor learns from r_t + η_k e^y_t, with e^y_t = Σ ρ_y Σ_i |y_{i,t} − ŷ_{i,t}| the observation
prediction error of the observation-predicting predictors at the step's new observation, and
η_k = η · max(0, 1 − k / (``curiosity_anneal`` · N)) (η = ``curiosity``; 0 = off). Returns and
every metric are measured on the raw reward.

TD into the memory (``td_to_memory`` = λ ≥ 0, 0 = off): after every episode the predictors' memory
parameters also take a step down −λ Σ_t δ_t Q(s_t, a_t) through the memory part of the actor's state
(``ferl.trainers.memory_td``), before the replay's BPTT steps.
"""

import numpy as np
import torch

from ferl.compiled import run_clock
from ferl.config.params import ConfigError, Momentum, NonNegative, PositiveInt, UnitInterval
from ferl.config.swaps import chosen
from ferl.exploration import added
from ferl.predictors.popart import observe_rewards
from ferl.predictors.recurrent import lookup_step
from ferl.replay import draw_episodes, store_episode, stored_episodes
from ferl.trainers.actor_episodes import ActorEpisodes
from ferl.trainers.episodes import episode_tensors
from ferl.trainers.handoffs import Episodes
from ferl.trainers.memory_td import check_td_to_memory, td_to_memory

# The replay's BPTT compiles for runs of this many episodes or more: an LSTM's replay step at
# T_max = 44 took 0.21 s eager and 0.08 s compiled after ~120 s of compiling (10 runs, 64 replayed
# episodes, another job on the second core), so shorter runs stay eager (docs/performance.md)
REPLAY_FUSED_FROM = 5000
# Its episodes compile for runs of this many episodes or more, in graphs of a few steps
# (``ferl.trainers.fused_episodes``): an LSTM predictor's episode at T_max = 44 took 0.050 s eager
# and 0.006 s compiled after 25 s of compiling from an empty cache (10 runs, one thread), repaid
# after ~600 episodes (docs/performance.md, "Graphs of fixed size")
EPISODES_FUSED_FROM = 1000


class OnlineEpisodes(ActorEpisodes):
    """``ActorEpisodes`` on live predictors that learn from a replay after every episode, with
    β following their held-out error and the curiosity bonus (module docstring). Records
    ``online.npz``: per run and episode the held-out error, β and η, and the phase's time split."""

    def __init__(
        self,
        replay_episodes: PositiveInt,
        replay_sample: PositiveInt,
        replay_batch_size: PositiveInt | None,
        beta_error_ratio: Momentum,
        error_ema: UnitInterval,
        curiosity: NonNegative,
        curiosity_anneal: NonNegative,
        td_to_memory: NonNegative = 0.0,
        **episodes,
    ):
        """``episodes``: ``ActorEpisodes``' own keys (its signature, which the config checks read too)."""
        super().__init__(**episodes)
        self.K, self.n_replay, self.replay_batch = replay_episodes, replay_sample, replay_batch_size
        self.tau, self.ema, self.eta, self.anneal = beta_error_ratio, error_ema, curiosity, curiosity_anneal
        self.td_to_memory = td_to_memory
        self.eta_now: torch.Tensor  # η_k, a 0-dim tensor that begin_episode fills (one graph serves every k)
        self.beta_now: torch.Tensor  # β_k per run (R, 1, 1): set by begin_episode

    def prepare(self, job) -> None:
        if self.td_to_memory > 0 and not job.predictors:
            raise ConfigError(
                f"trainer.td_to_memory={self.td_to_memory:g} is not allowed with predictor=none: "
                f"{chosen('trainer', 'OnlineEpisodes')} has no memory to train without a predictor; 0 turns it off"
            )
        if self.td_to_memory > 0:
            check_td_to_memory(job, self.td_to_memory)
        if job.predictors:  # the replay keeps the ids of the last K episodes, with the one being played
            job.env.keep_episodes(self.K + 1, "trainer.replay_episodes")
        super().prepare(job)
        self.eta_now = torch.zeros((), device=job.device)
        self.fused_replay = self.fuses_replay(job)
        groups: dict = {}
        for p in job.predictors.values():
            groups.setdefault(p.batch_key, []).append(p)
        self.groups = list(groups.values())

    def fresh_state(self, job) -> dict:
        R, K, T = job.R, self.K, job.env.max_steps
        zeros = lambda *shape, **kw: torch.zeros(R, K, *shape, device=job.device, **kw)  # noqa: E731
        return {
            **super().fresh_state(job),
            "replay": {
                "obs": zeros(T + 1, dtype=torch.long) - 1,
                "actions": zeros(T, dtype=torch.long),
                "rewards": zeros(T),
                "lengths": zeros(dtype=torch.long),
            },
            "error_first": None,
            "error_ema": None,
            "predictor_time": 0.0,
            "online": {k: np.zeros((R, self.N), np.float32) for k in ("prediction_error", "beta", "curiosity")},
        }

    def fuses(self, job) -> bool:
        """As the actor phase's episodes (``ActorEpisodes.fuses``), for runs of at least
        EPISODES_FUSED_FROM episodes: β_k and η_k are tensors (one graph serves every episode), and
        the live predictors' steps read their weights as the replay leaves them."""
        return super().fuses(job) and self.N >= EPISODES_FUSED_FROM

    def fuses_replay(self, job) -> bool:
        """Whether the replay's BPTT steps run as compiled graphs (``PredictorBatch.fuse``: graphs
        of whole SGD steps over short episodes, of a fixed number of time steps over long ones): on
        the fast path, for runs of at least REPLAY_FUSED_FROM episodes, the ones whose saving
        repays the compiling (module constant)."""
        return job.fast and self.N >= REPLAY_FUSED_FROM

    def memory_step(self, predictor, table: torch.Tensor, n_actions: int):
        """The predictor's step with its current weights (they learn between episodes)."""
        return lookup_step(predictor, table, n_actions)

    def begin_episode(self, job, k: int, state: dict):
        """β_k per run (R, 1, 1) from the error so far, and η_k (module docstring). Without a
        predictor (``predictor=none``) there is no error to wait for: β_k is the actor's schedule,
        as in Algorithm 1's actor phase."""
        self.eta_now.fill_(self.eta * max(0.0, 1.0 - k / (self.anneal * self.N)) if self.anneal > 0 else self.eta)
        base = job.actor.inverse_temperature(k / self.N)
        if not job.predictors:
            self.beta_now = torch.full((job.R, 1, 1), float(base), device=job.device)
        elif state["error_first"] is None:
            self.beta_now = torch.zeros(job.R, 1, 1, device=job.device)
        else:
            share = (1 - state["error_ema"] / state["error_first"].clamp(min=1e-12)) / (1 - self.tau)
            self.beta_now = (base * share.clamp(0, 1)).view(-1, 1, 1)
        return self.beta_now

    @torch.no_grad()
    def reward_bonus(self, job, states: list, obs_id: torch.Tensor, s_next: torch.Tensor, active: torch.Tensor):
        """η_k e^y_t: the observation prediction error at the new observation (module docstring),
        plus the directed exploration's bonus (``ActorEpisodes.reward_bonus``). Computed with
        curiosity off too (η = 0, a bonus of exactly 0, whatever e^y_t), so that a compiled
        episode's graph serves every η."""
        explore = super().reward_bonus(job, states, obs_id, s_next, active)
        y = self.observations.lookup(obs_id)
        errors = [p.observation_error(x, y) for p, x in zip(job.predictors.values(), states)]
        errors = [e for e in errors if e is not None]  # the predictors that predict observations
        if not errors:
            return explore
        return added(torch.where(self.eta_now > 0, self.eta_now * sum(errors), 0.0), explore)

    def after_episode(self, job, k: int, episode: dict, state: dict) -> None:
        """Held-out error of episode k, then into the replay, then the predictors' BPTT steps.
        Without a predictor only β is recorded (its error is NaN): nothing else learns."""
        if not job.predictors:
            state["online"]["prediction_error"][:, k] = np.nan
            state["online"]["beta"][:, k] = self.beta_now.flatten().cpu().numpy()
            return
        started = run_clock()  # compiling is left out, as from the phase's active time
        ep = self.as_episodes(job, episode)
        with torch.no_grad():
            error = sum(
                (
                    torch.nanmean(p.prediction_errors(*episode_tensors(job, ep, p)).flatten(1), 1)
                    for p in job.predictors.values()
                ),
                torch.zeros((), device=job.device),
            )
        if state["error_first"] is None:
            state["error_first"] = state["error_ema"] = error
        else:
            state["error_ema"] = torch.lerp(state["error_ema"], error, self.ema)
        online = state["online"]
        online["prediction_error"][:, k] = error.cpu().numpy()
        online["beta"][:, k] = self.beta_now.flatten().cpu().numpy()  # the β episode k acted with
        online["curiosity"][:, k] = float(self.eta_now)
        observe_rewards(
            job.predictors.values(), ep.rewards, ep.lengths
        )  # once per new episode, after its held-out error
        if self.td_to_memory > 0:
            self.memory_td(job, ep, episode)
        replay = state["replay"]
        store_episode(
            replay,
            k,
            {
                "obs": ep.obs[:, 0],
                "actions": ep.actions[:, 0],
                "rewards": ep.rewards[:, 0],
                "lengths": ep.lengths[:, 0],
            },
        )
        pick = draw_episodes(replay, k + 1, self.n_replay, job.generator, job.device)
        sample = Episodes(**stored_episodes(replay, pick))
        order = torch.arange(self.n_replay, device=job.device).expand(job.R, -1)
        y, a, _, lengths = episode_tensors(job, sample, None)
        for members in self.groups:
            rs = [p.reward_targets(job.env.reward_values, sample.rewards) for p in members]
            batch = type(members[0]).training_batch(members, y, a, rs, lengths, self.replay_batch, summed=True)
            if self.fused_replay:  # one graph for every replay: short episodes unrolled to T_max
                batch.fuse(job.device, unroll_to=job.env.max_steps)
            batch.train_epoch([order] * len(members))
        state["predictor_time"] += run_clock() - started
        if (k + 1) % self.log_every == 0:
            window = slice(max(0, k + 1 - self.final_window), k + 1)
            for key, values in online.items():
                job.writer.add_scalar(f"online/{key}_ma{self.final_window}", float(values[:, window].mean()), k + 1)

    def memory_td(self, job, ep: Episodes, episode: dict) -> None:
        """The TD step into the predictors' memory on the episode just played (``ferl.trainers.memory_td``)."""
        states, actions, deltas = episode["states"], episode["trajectory"][1], episode["td"]
        n = actions.shape[0]
        deltas = torch.where(deltas.isfinite() & job.guard.alive.T, deltas, 0.0)  # NaN: the run's episode had ended
        y, a, _, lengths = episode_tensors(job, ep, None)
        predictors = list(job.predictors.values())
        td_to_memory(
            predictors, job.actor, y[:, :, : n + 1], a[:, :, :n], lengths, states, actions, deltas, self.td_to_memory
        )

    def as_episodes(self, job, episode: dict) -> Episodes:
        """The trajectory of ``play_episode`` as one padded episode per run, (R, 1, …)."""
        obs, actions, rewards = episode["trajectory"]
        T, lengths = job.env.max_steps, episode["lengths"].long()
        steps = torch.arange(T + 1, device=job.device).unsqueeze(1)
        pad = lambda x, fill: torch.nn.functional.pad(x, (0, 0, 0, T + 1 - x.shape[0]), value=fill)  # noqa: E731
        obs = torch.where(steps <= lengths, pad(obs, -1), -1)
        actions = torch.where(steps[:-1] < lengths, pad(actions, 0)[:-1], 0)
        rewards = torch.where(steps[:-1] < lengths, pad(rewards, 0.0)[:-1], 0.0)
        return Episodes(obs.T.unsqueeze(1), actions.T.unsqueeze(1), rewards.T.unsqueeze(1), lengths.unsqueeze(1))

    def finish(self, job, state: dict) -> None:
        super().finish(job, state)
        job.run.save_records(
            "online",
            job.R,
            **state["online"],
            predictor_time_s=np.float64(state["predictor_time"]),
            actor_time_s=np.float64(state["active_time"] - state["predictor_time"]),
        )
