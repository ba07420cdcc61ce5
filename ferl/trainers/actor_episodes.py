"""Algorithm 1's actor phase (§4.2, §4.3.1): episodes of the actor on the frozen predictors' memory.

All runs of the batch play their episodes in lockstep: episode k of every run starts together,
runs whose episode has ended wait (their TD errors are masked) until the slowest has finished.
The action uniforms of an episode are drawn for all T_max + 1 choices when it starts, so no run's
episode length shifts another run's random stream. The actor's state is the (processed)
observation, scaled by ``actor_obs_scale``, followed by every predictor's memory; the frozen
predictors step on observation ids (``Predictor.frozen_step``).

What the records keep besides returns, lengths and TD errors is the environment's: its episode
``outcomes`` (per episode, in ``episodes.npz``; the boolean ones give ``final_<name>_rate`` and
count towards ``solved``) and the activations at its ``probe`` states with its ``labels``
(``probe.npz``: the T-junction in the T-mazes, Figs. 4.14–4.19; named for what every episodic
environment may declare, docs/records.md).
"""

import numpy as np
import torch
from tqdm import tqdm

from ferl.actors.td import first_action, td_step
from ferl.compiled import compiled, run_clock
from ferl.config.params import Positive, PositiveInt
from ferl.interfaces import EndedEpisode
from ferl.predictors.heads import scaled
from ferl.random_blocks import Blocks, steps_per_block
from ferl.run.directory import CheckpointTimer
from ferl.stats import final_metrics, has_goal, sample_efficiency, solved_against
from ferl.trainers.actor_logs import (
    concat_records,
    log_actor,
    log_episodes,
    log_probes,
    probe_visits,
    progress_postfix,
)
from ferl.trainers.episodes import Carry, Step, discount_factors, observation_table, played, returned, stacked
from ferl.trainers.fused_episodes import FusedEpisodes, as_beta
from ferl.trainers.observations import log_observations
from ferl.trainers.phased import Phase


class ActorEpisodes(Phase):
    """``n_episodes`` SARSA(0) episodes (α, β by the actor's schedules over the episodes), logged
    every ``log_every`` episodes, checkpointed every ``checkpoint_every`` (and by the clock, every
    ``checkpoint_minutes``; these three from the trainer's run node, ``job.control``); every
    ``td_sample_every``-th episode keeps its per-step TD errors; the metrics are taken over the
    last ``final_window`` episodes. The actor's observation is scaled by ``actor_obs_scale``."""

    def __init__(
        self,
        n_episodes: PositiveInt,
        actor_obs_scale: Positive,
        td_sample_every: PositiveInt,
        final_window: PositiveInt,
    ):
        self.N, self.obs_scale, self.last_step = n_episodes, actor_obs_scale, n_episodes
        self.td_sample_every, self.final_window = td_sample_every, final_window

    def start(self, job) -> None:
        log_observations(job)

    def prepare(self, job) -> None:
        control = job.control
        self.log_every, self.checkpoint_every, self.checkpoint_minutes = (
            control.log_every,
            control.checkpoint_every,
            control.checkpoint_minutes,
        )
        steps = job.env.max_steps + 1  # an episode's action draws: a_0 … a_{T_max}
        width = max(1, job.actor.uniforms_per_action)  # 1 for a softmax; a Gibbs chain's every draw
        self.uniforms = Blocks(
            lambda n: (torch.rand(n, steps, job.R, 1, width, generator=job.generator, device=job.device),),
            steps_per_block(steps * job.R * width),
        )
        job.unit = "episode"
        outcomes = job.env.outcomes()
        self.outcome_names = ("discounted_return", "steps", "terminal_reward", "td_abs_mean", *outcomes)
        self.rates = [name for name, v in outcomes.items() if v.dtype == torch.bool]  # e.g. correct_goal
        self.averages = [name for name, v in outcomes.items() if v.is_floating_point()]  # e.g. a return
        optimal = job.env.optimal(job.actor.gamma)
        self.optimum, self.goal = solved_against(optimal), has_goal(optimal)
        kinds = {
            **{k: np.int64 for k in outcomes},
            **{k: bool for k in self.rates},
            **{k: np.float32 for k in self.averages},
        }
        self.dtypes = {
            "discounted_return": np.float32,
            "steps": np.int64,
            "terminal_reward": np.float32,
            "td_abs_mean": np.float32,
            **kinds,
        }

    def metric_names(self, job) -> list[str]:
        solved = ["solved"] if self.optimum else []
        return [
            "final_discounted_return",
            *(["final_steps_to_goal"] if self.goal else []),  # an env with a goal only (ferl.stats.has_goal)
            *(f"final_{name}_rate" for name in self.rates),
            *(f"{when}_{name}" for name in self.averages for when in ("final", "best")),
            *solved,
            "env_steps_total",
            *(["env_steps_to_solve", "episodes_to_solve"] if self.optimum else []),
        ]

    def fresh_state(self, job) -> dict:
        """Records of the phase before its first episode: one value per run and episode."""
        R, N, T_max = job.R, self.N, job.env.max_steps
        n_sampled = len(range(0, N, self.td_sample_every))
        return {
            "episode": 0,
            "records": {k: np.zeros((R, N), dtype=self.dtypes[k]) for k in self.outcome_names},
            "probes": [],
            "active_time": 0.0,
            "agent_steps": 0,
            "td_sampled": np.full((R, n_sampled, T_max), np.nan, dtype=np.float32),
        }

    def run(self, job, state) -> None:
        """Episodes from where a checkpoint left them."""
        if state is None:
            log_actor(job, 0)
            state = self.fresh_state(job)
        else:
            self.uniforms.load_state_dict(state.pop("uniforms"), job.device)
        records, td_sampled, probes = state["records"], state["td_sampled"], state["probes"]
        self.freeze(job)
        clock = CheckpointTimer(self.checkpoint_minutes)
        bar = tqdm(
            range(state["episode"], self.N),
            desc="actor",
            unit="episode",
            initial=state["episode"],
            total=self.N,
            mininterval=1.0,
        )
        for k in bar:
            started = run_clock()
            lr, beta = job.actor.learning_rate(k / self.N), self.begin_episode(job, k, state)
            episode = self.play_episode(job, k, lr, beta)
            self.after_episode(job, k, episode, state)
            state["active_time"] += run_clock() - started
            outcome = episode["outcome"].cpu().numpy()  # one host copy per episode
            for i, key in enumerate(self.outcome_names):
                records[key][:, k] = outcome[i]
            state["agent_steps"] += int(records["steps"][:, k].sum())
            if episode["probes"] is not None:
                probes.append(episode["probes"])
            if k % self.td_sample_every == 0:
                td = episode["td"].T.cpu().numpy()
                td_sampled[:, k // self.td_sample_every, : td.shape[1]] = td
            if (k + 1) % self.log_every == 0 or k + 1 == self.N:
                checked = k + 1 - (k % self.log_every + 1)  # first episode not yet checked
                job.guard.check(torch.as_tensor(records["td_abs_mean"][:, checked : k + 1].T), checked, "episode")
            if (k + 1) % self.log_every == 0:
                log_episodes(
                    job.writer, self.final_window, self.rates, records, k + 1, lr, float(torch.as_tensor(beta).mean())
                )
                postfix = progress_postfix(records, k + 1, self.final_window, self.rates, self.averages)
                bar.set_postfix(postfix, refresh=False)
            if ((k + 1) % self.checkpoint_every == 0 or job.stop.requested or clock.due()) and k + 1 < self.N:
                state["probes"] = probes = [concat_records(probes)] if probes else []
                state["episode"] = k + 1
                job.checkpoint(self.name, {**state, "uniforms": self.uniforms.state_dict()})
        bar.close()
        self.finish(job, state)

    def begin_episode(self, job, k: int, state: dict):
        """β of episode k: the actor's schedule (§4.3.1)."""
        return job.actor.inverse_temperature(k / self.N)

    def after_episode(self, job, k: int, episode: dict, state: dict) -> None:
        """What learns from episode k besides the actor: nothing while the predictors are frozen."""

    def reward_bonus(self, job, states: list, obs_id: torch.Tensor, s_next: torch.Tensor, active: torch.Tensor):
        """Added to the raw reward the actor learns from: the directed exploration's bonus, or None."""
        return job.exploration.reward_bonus(s_next, active) if job.exploration.active else None

    def memory_step(self, predictor, table: torch.Tensor, n_actions: int):
        """A predictor's step on observation ids: the frozen one (``Predictor.frozen_step``)."""
        return predictor.frozen_step(table, n_actions)

    def freeze(self, job) -> None:
        """The predictors' steps on observation ids, the actor's observation rows (times
        ``actor_obs_scale``) and the row offsets that address run r's part of them."""
        self.observations = observation_table(job)
        table = self.observations.table
        ids = job.env.observation_table.shape[0]
        self.steps_on_ids = [self.memory_step(p, table, job.env.n_actions) for p in job.predictors.values()]
        # scaled once; an environment that discovers its observations fills the table in place, so
        # its rows are indexed live and scaled at each step (a gain of 1 costs nothing either way)
        rows = table.reshape(-1, table.shape[-1])
        live = job.env.discovers_observations
        self.obs_rows, self.row_gain = (rows, self.obs_scale) if live else (scaled(rows, self.obs_scale), 1.0)
        self.obs_offsets = torch.arange(job.R, device=job.device) * ids if table.dim() == 3 else None
        factors = discount_factors(job.actor.gamma, job.env.max_steps)
        self.discount_table = torch.tensor(factors, dtype=torch.float64, device=job.device)
        self.fused, self.agent = None, self.agent_step
        if job.fast:  # what the actor learns after an episode, however the episodes are played
            job.actor.compile_updates(job.device)
        if self.fuses(job):
            job.actor.prepare_for_compile()
            if job.env.traceable_steps:
                self.fused = FusedEpisodes(self, job)
            else:  # a Python environment (env=gymnasium): its step eager, the agent's half one graph
                self.agent = compiled(self.agent_step, job.device, "the agent's half of a step")

    def fuses(self, job) -> bool:
        """Whether episodes run as compiled graphs of a fixed size (``ferl.compiled``): on the fast
        path, with an actor that chooses by one number a step (a Gibbs chain's sweeps, unrolled in
        every step, would make the graph too large to compile in a run's time). A tensor
        environment (``traceable_steps``) is traced with the agent in chunks of a few steps; another
        (``env=gymnasium``) steps eagerly between calls of one graph of ``agent_step``. An actor's
        memory stepped in place (the recurrent Q-learner's buffers) is written back by the graph."""
        return (
            job.fast
            and job.actor.uniforms_per_action == 1
            # a directed exploration whose hooks keep Python state (counts) runs eagerly
            and (not job.exploration.active or job.exploration.traceable)
        )

    def state(self, job, obs_id: torch.Tensor, memories: list) -> torch.Tensor:
        """The actor's state (R, 1, S): the (processed) observation, then every predictor's memory."""
        return torch.cat([self.observed(obs_id, self.obs_offsets), *memories], 1).unsqueeze(1)

    def observed(self, obs_id: torch.Tensor, offsets: torch.Tensor | None) -> torch.Tensor:
        """The actor's rows (n, Y) of observation ids (n,), whose runs' parts of a per-run table
        start at ``offsets`` (n,), or None for a table shared by the runs."""
        rows = obs_id if offsets is None else obs_id + offsets
        return scaled(self.obs_rows.index_select(0, rows), self.row_gain)

    def play_episode(self, job, k: int, lr: float, beta: float) -> dict:
        """Episode k of every run (``episode``), in compiled chunks on the fast path
        (``ferl.trainers.fused_episodes``), and what the records keep of it: the outcome
        (len(outcome_names), R), the TD errors (steps, R), NaN where a run had ended, the probe
        visits (or None), the trajectory: observation ids (steps + 1, R), actions (steps, R) and raw
        rewards (steps, R), and the actor's states (steps, R, S)."""
        job.env.reset()
        (uniform,) = self.uniforms.next()  # (T_max + 1, R, 1, uniforms_per_action)
        job.exploration.begin_episode(job.generator, job.env.max_steps, k / self.N)  # its draws after the actor's
        if self.fused is None and self.agent != self.agent_step:  # compiled: α and β as tensors, one graph
            ep = self.episode(job, torch.tensor(lr, device=job.device), as_beta(beta, job.device), uniform, True)
        elif self.fused is None:
            ep = self.episode(job, lr, beta, uniform, True)
        else:
            ep = self.fused.play(self, job, lr, beta, uniform)
        job.actor.end_episode(self.ended_episode(job, ep), lr)
        return {
            "outcome": ep["outcome"],
            "lengths": ep["lengths"].clone(),
            "td": torch.where(ep["actives"], ep["deltas"], torch.nan),
            "probes": probe_visits(job, k, ep),
            "trajectory": (ep["obs"], ep["actions"], ep["rewards"]),
            "states": ep["states"],  # (steps, R, S) the actor's state at every step
        }

    def episode(self, job, lr, beta, uniform, until_done: bool) -> dict:
        """An episode of every run from the reset environment, with SARSA(0) updates at every step
        (``steps``); ``uniform`` (T_max + 1, R, 1, ``uniforms_per_action``) the action draws.
        ``until_done``: stop once every run has ended (eager); else play all T_max steps, the
        ended ones masked. Returns ``played``'s dict. The readable reference of the fast path, which
        plays the same steps in graphs of a fixed number of them."""
        obs = job.env.obs_id
        carry = self.first(job, beta, uniform[0])
        carry, steps, after = self.steps(job, carry, lr, beta, uniform[1:], self.discount_table, until_done)
        return played(job.env, carry, steps, torch.cat([obs.unsqueeze(0), after]))

    def first(self, job, beta, uniform) -> Carry:
        """Where an episode's TD steps start: m_0 (Eq. 4.1; it learns too when the predictors do),
        the state s_0 and a_0 of every run (``first_action``) by the draws ``uniform`` (R, 1, ·)."""
        env, actor, predictors = job.env, job.actor, list(job.predictors.values())
        choose = job.exploration.choose if job.exploration.active else None  # directed exploration
        m = [p.initial_state() for p in predictors]
        memories = [p.memory(x) for p, x in zip(predictors, m)]
        s = self.state(job, env.obs_id, memories)
        a, F_sa, x_sa = first_action(actor, s, beta, job.generator, uniform, choose)
        zeros = torch.zeros(env.done.shape, dtype=torch.float64, device=env.done.device)
        return Carry(m, memories, s, a, F_sa, x_sa, torch.zeros_like(env.done), zeros)

    def steps(self, job, carry: Carry, lr, beta, uniform, discounts, until_done: bool):
        """len(``uniform``) steps of every run from ``carry``: observe → memories m_t (Eq. 4.3) →
        a' by Eq. (3.11) → δ → θ update (Eq. 3.10) (``td_step``), with the draws ``uniform``
        (n, R, 1, ·) and the discounts γ^t (n,) (float64) of the steps' times. Runs whose episode
        has ended wait with δ = 0 and keep their parameters. The return R_0^γ = Σ_t γ^t r_(t+1)
        (Eq. 2.37) accumulates in float64 step by step (``returned``). Returns the
        carry after them, the steps stacked (``Step``, (n, R, …)) and the observation ids after
        each step (n, R); with ``until_done``, fewer steps once every run has ended."""
        env = job.env
        m, memories, s, a, F_sa, x_sa, terminated_any, ret = carry
        record, obs = [], []
        for t in range(len(uniform)):
            active = ~env.done
            visit = (env.probe & active, active, tuple(memories), s[:, 0], x_sa[:, 0])  # before the step
            obs_prev, action = env.obs_id, a.squeeze(1)
            r, terminated, _ = env.advance(action)
            terminated_any = terminated_any | terminated
            ret = returned(ret, discounts[t], r)  # done runs got r = 0
            obs.append(env.obs_id)
            ended = terminated | ~active
            m, memories, s_next, a, F_sa, x_sa, delta = self.agent(
                job, m, s, a, F_sa, x_sa, obs_prev, action, env.obs_id, r, ended, active, lr, beta, uniform[t]
            )
            record.append(Step(*visit, action, r, delta.squeeze(1)))
            s = s_next
            if until_done and bool(env.done.all()):
                break
        carry = Carry(m, memories, s, a, F_sa, x_sa, terminated_any, ret)
        return carry, stacked(record), torch.stack(obs)

    def agent_step(self, job, m, s, a, F_sa, x_sa, obs_prev, action, obs_id, r, ended, active, lr, beta, uniform):
        """The agent's half of a step after the environment's (``steps``): predictors' states m_(t+1)
        from ids ``obs_prev`` and ``action`` (R,) (Eq. 4.3), s_(t+1) at ``obs_id``, a_(t+1) by Eq.
        (3.11) with draws ``uniform`` (R, 1, ·), δ_t on ``r`` plus any bonus and the θ update (Eq.
        3.10; ``td_step``; ``ended``: no s_(t+1) to bootstrap from). One graph where the environment
        cannot be traced (``freeze``). Returns m, the memories, s_(t+1), a_(t+1), F, the cache, δ."""
        predictors = list(job.predictors.values())
        choose = job.exploration.choose if job.exploration.active else None
        m = [step(x, obs_prev, action) for step, x in zip(self.steps_on_ids, m)]
        memories = [p.memory(x) for p, x in zip(predictors, m)]
        s_next = self.state(job, obs_id, memories)
        bonus = self.reward_bonus(job, m, obs_id, s_next, active)
        a, F_sa, x_sa, delta = td_step(
            job.actor,
            s,
            a,
            F_sa,
            x_sa,
            r if bonus is None else r + bonus,
            s_next,
            lr,
            beta,
            job.generator,
            uniform,
            job.guard.alive,
            ended.unsqueeze(1),
            active.unsqueeze(1),
            choose,
        )
        return m, memories, s_next, a, F_sa, x_sa, delta

    def ended_episode(self, job, ep: dict) -> EndedEpisode:
        """The episode that ``episode`` played, as the actor's ``end_episode`` takes it (laid out
        per run only where the actor asks, ``EndedEpisode.padded``: most actors learn per step)."""
        states, last, actions, rewards = ep["states"], ep["last_state"], ep["actions"], ep["rewards"]
        return EndedEpisode(states, last, actions, rewards, ep["lengths"], ep["terminated"], job.env.max_steps)

    def visit_states(self, job, visits: dict) -> dict:
        """The probe records with the actor's state at every visit (visits, S) in the place of its
        observation id: rebuilt as ``state`` built it (``observed``), from the id and the memories
        recorded with it, in float16 as they are (a float16 conversion is element-wise: the same
        numbers as the state's). The phase and its checkpoints hold an id a visit, not S numbers: 784 pixels in
        the digit mazes, where the state made the checkpoints hundreds of MB. Visits that hold
        their states (a checkpoint of an earlier ferl) are kept as they are."""
        if "observation" not in visits:
            return visits
        offsets = None if self.obs_offsets is None else self.obs_offsets[visits["run"].to(job.device)]
        observed = self.observed(visits["observation"].to(job.device), offsets).half().cpu()
        memories = [visits[f"memory_{name}"] for name in job.predictors]
        rebuilt = {}
        for key, v in visits.items():  # in the records' order: the state where its id was
            if key == "observation":
                key, v = "state", torch.cat([observed, *memories], 1)
            rebuilt[key] = v
        return rebuilt

    def finish(self, job, state: dict) -> None:
        """Records, metrics, the final TensorBoard points; the phase's steps for the speed."""
        records = state["records"]
        log_actor(job, self.N)
        visits = self.visit_states(job, concat_records(state["probes"])) if state["probes"] else {}
        probes = {key: v.numpy() for key, v in visits.items()}
        if probes:
            probes["steps_to_goal"] = records["steps"][probes["run"], probes["episode"]]
        sampled = np.asarray(list(range(0, self.N, self.td_sample_every)))
        optimal = job.env.optimal(job.actor.gamma)
        job.run.save_records(
            "episodes",
            job.R,
            **records,
            td_sampled=state["td_sampled"],
            td_sampled_episodes=sampled,
            gamma=np.float64(job.actor.gamma),
            optimal_return=np.float64(optimal.get("discounted_return", np.nan)),
            optimal_steps=np.float64(job.env.optimal_steps),
            final_window=np.int64(self.final_window),
        )
        job.run.save_records("probe", job.R, **probes)
        log_probes(job, probes, records, self.rates, self.N)
        job.metrics.update(
            final_metrics(records, self.optimum, self.final_window, self.rates, self.averages, goal=self.goal)
        )
        random_steps = job.outputs.random_steps  # None: no random collection before
        if random_steps is None:
            random_steps = np.zeros(job.R, np.int64)
        job.metrics.update(sample_efficiency(records, random_steps, self.optimum, self.final_window, self.rates))
        job.count_agent_steps(state["agent_steps"], state["active_time"])
