"""Online TD training on a continuing task (§3.2, §3.5): every run steps and learns at once.

One training step for every run:  observe s' → F(s', ·) for all actions → sample a' (Eq. 3.11)
→ δ = r − γ F(s', a') + F(s, a) → θ ← θ + α δ (−∂F/∂θ) (Eq. 3.10)  (``ferl.actors.td``), in
chunks of steps on random numbers drawn beforehand (``ferl.trainers.chunks``). α and β follow the
actor's schedules over the phase's steps. The environment is any with ``step_inputs`` /
``step_with`` (a step's random numbers as inputs, so a chunk can be compiled) and ``slice_runs``.
"""

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

import numpy as np
import torch
from tqdm import tqdm

from ferl.actors.td import first_action
from ferl.compiled import run_clock
from ferl.config.params import ConfigError, NonNegativeInt, PositiveInt
from ferl.interfaces import ActorViews
from ferl.random_blocks import Blocks, steps_per_block
from ferl.run.directory import CheckpointTimer
from ferl.trainers.chunks import MAX_CHUNK, chunk_length, compiled_td_steps, done_future, switch_interval, td_steps
from ferl.trainers.phased import Phase

# Prefetching pays from a few tens of runs on (compile=true, agent-steps/s drawn in turn → ahead:
# 100 runs 157 k → 225–300 k, 30 runs 162–190 k → 230–257 k); at 10 runs it gains nothing and varies
# (160 k → 141–169 k), and a single run's chunk is too short to hide the thread handoff (48 k → 30 k).
PREFETCH_MIN_RUNS = 30
# How long a thread holds the GIL while the other waits for it: at Python's 5 ms default, chunks of
# 10 and 30 runs (1–3 ms) waited for it more than prefetching saved (10 runs: 156 k → 119–128 k
# agent-steps/s; 30 runs, one chunk ahead: 162 k → 135 k).
SWITCH_INTERVAL_S = 2e-4


class ContinuingTD(Phase):
    """``steps`` online TD steps of every run on a continuing task, logged every ``log_every`` and
    checkpointed every ``checkpoint_every`` steps (and every ``checkpoint_minutes``: the trainer's
    run node, ``job.control``). ``compile``: the chunk as one torch.compiled graph, by groups of
    ``compile_group_runs`` runs on a CPU; ``prefetch``: chunks of random numbers drawn ahead on a
    second thread (from PREFETCH_MIN_RUNS runs on, and not when the actor draws inside a step).
    Records ``steps.npz`` (reward and TD error of every step) and ``weights.npz`` (the actor's
    state weights before and after); metric ``reward_per_step_last10pct``."""

    def __init__(self, steps: PositiveInt, compile_group_runs: PositiveInt, prefetch: NonNegativeInt):
        self.T, self.last_step = steps, steps
        self.compile_group_runs, self.prefetch_chunks = compile_group_runs, prefetch

    def prepare(self, job) -> None:
        actor, R, control = job.actor, job.R, job.control
        self.log_every, self.checkpoint_every, self.checkpoint_minutes = (
            control.log_every,
            control.checkpoint_every,
            control.checkpoint_minutes,
        )
        if actor.learns_from_episodes:
            raise ConfigError(
                f"actor={actor.describe()['kind']} learns from whole episodes, and the continuing task "
                f"{job.env.task} has none: use an episodic environment or another actor"
            )
        # a choice's uniforms: 1 for a softmax, a whole Gibbs chain's draws (the large-action task)
        width = max(1, actor.uniforms_per_action)
        self.action_uniforms = Blocks(
            lambda steps: (torch.rand(steps, R, 1, width, generator=job.generator, device=job.device),),
            steps_per_block(R * width),
        )
        # a Gibbs chain unrolls its sweeps in the graph (100 a step in the large-action task): one
        # step a chunk keeps the graph's compile time that of one chain (docs/performance.md)
        most = MAX_CHUNK if width == 1 else 1
        self.chunk = chunk_length(self.T, self.log_every, self.checkpoint_every, most=most)
        self.td_steps = td_steps
        if job.fast and actor.uniforms_per_action > 0:  # an actor that draws inside a step: eager
            actor.prepare_for_compile()
            self.td_steps = compiled_td_steps(R, self.compile_group_runs, job.device)
        drawn_ahead = actor.uniforms_per_action > 0 and R >= PREFETCH_MIN_RUNS
        self.prefetch = self.prefetch_chunks if drawn_ahead else 0

    def metric_names(self, job) -> list[str]:
        return ["reward_per_step_last10pct"]

    def fresh_state(self, job) -> dict:
        """State at step 0: the first observation and action, the initial state weights (where the
        actor shows them, ``ActorViews``)."""
        s = job.env.reset().unsqueeze(1)
        a, F_sa, x_sa = first_action(
            job.actor, s, job.actor.inverse_temperature(0.0), job.generator, *self.action_uniforms.next()
        )
        views = isinstance(job.actor, ActorViews)
        return {
            "step": 0,
            "state_weights_before": job.actor.state_weights().cpu().clone() if views else None,
            "s": s,
            "a": a,
            "F_sa": F_sa,
            "x_sa": x_sa,
            "rewards": torch.zeros(self.T, job.R, device=job.device),
            "td_errors": torch.zeros(self.T, job.R, device=job.device),
            "actor_time": 0.0,
            "checked": 0,
        }  # steps whose TD errors the divergence guard has seen

    def chunk_inputs(self, env) -> tuple:
        """The random numbers of one chunk: action uniforms, then the environment's."""
        return (*self.action_uniforms.take(self.chunk), *env.step_inputs(self.chunk))

    def run(self, job, state) -> None:
        if state is None:
            state = self.fresh_state(job)
        else:
            self.action_uniforms.load_state_dict(state.pop("action_uniforms"), job.device)
            state = {
                k: v.to(job.device) if torch.is_tensor(v) and k != "state_weights_before" else v
                for k, v in state.items()
            }
            state["inputs"] = [tuple(x.to(job.device) for x in inputs) for inputs in state.get("inputs", ())]
        state = self.train(job, state)
        self.finish(job, state)

    def train(self, job, state: dict) -> dict:
        """The steps from state["step"] to T; returns the final state."""
        actor, env, T = job.actor, job.env, self.T
        s, a, F_sa, x_sa = state["s"], state["a"], state["F_sa"], state["x_sa"]
        rewards, td_errors = state["rewards"], state["td_errors"]
        clock = CheckpointTimer(self.checkpoint_minutes)
        bar = tqdm(total=T, initial=state["step"], desc=self.name, unit="step", mininterval=1.0, dynamic_ncols=True)
        started = run_clock()
        # random inputs of the next chunks, in draw order; a checkpoint's were drawn before the
        # generator state it saved
        pending = deque(done_future(inputs) for inputs in state.pop("inputs", ()))
        drawn_to = state["step"] + self.chunk * len(pending)  # the first step not yet drawn for
        with (
            ThreadPoolExecutor(1, thread_name_prefix="ferl-random") as worker,
            switch_interval(SWITCH_INTERVAL_S) if self.prefetch else nullcontext(),
        ):
            for t in range(state["step"], T, self.chunk):
                while drawn_to < min(T, t + (self.prefetch + 1) * self.chunk):
                    pending.append(
                        worker.submit(self.chunk_inputs, env) if self.prefetch else done_future(self.chunk_inputs(env))
                    )
                    drawn_to += self.chunk
                inputs = pending.popleft().result()
                progress = [(t + k) / T for k in range(self.chunk)]
                lrs = torch.tensor([actor.learning_rate(p) for p in progress], device=job.device)
                betas = torch.tensor([actor.inverse_temperature(p) for p in progress], device=job.device)
                out = self.td_steps(actor, env, job.generator, s, a, F_sa, x_sa, job.guard.alive, lrs, betas, *inputs)
                s, a, F_sa, x_sa = out.s, out.a, out.F_sa, out.x_sa
                rewards[t : t + self.chunk], td_errors[t : t + self.chunk] = out.rewards, out.deltas
                done = t + self.chunk
                if done % self.log_every == 0 or done == T:
                    job.guard.check(td_errors[state["checked"] : done], state["checked"])
                    state["checked"] = done
                    self.log(job.writer, rewards, td_errors, done, float(lrs[-1]), float(betas[-1]))
                    bar.set_postfix(reward_ma100=f"{rewards[max(0, done - 100) : done].mean():.2f}", refresh=False)
                    bar.update(done - bar.n)
                if (done % self.checkpoint_every == 0 or job.stop.requested or clock.due()) and done < T:
                    state.update(
                        step=done,
                        s=s,
                        a=a,
                        F_sa=F_sa,
                        x_sa=x_sa,
                        inputs=[f.result() for f in pending],
                        actor_time=state["actor_time"] + run_clock() - started,
                    )
                    started = run_clock()
                    job.checkpoint(self.name, {**state, "action_uniforms": self.action_uniforms.state_dict()})
                    del state["inputs"]  # in the checkpoint only
        bar.close()
        state["actor_time"] += run_clock() - started
        return state

    def log(self, writer, rewards, td_errors, done, lr, beta) -> None:
        """Fig. 3.4's 100-step moving average (mean and spread over runs), TD error, α, β."""
        window = rewards[max(0, done - 100) : done].mean(0)
        recent_td = td_errors[max(0, done - self.log_every) : done].abs().mean()
        for name, value in {
            "reward_ma100": window.mean(),
            "reward_ma100_std": window.std(correction=0),
            "reward_ma100_min": window.min(),
            "reward_ma100_max": window.max(),
            "td_error_abs": recent_td,
        }.items():
            writer.add_scalar(f"actor/{name}", value.item(), done)
        writer.add_scalar("schedule/learning_rate", lr, done)
        writer.add_scalar("schedule/beta", beta, done)

    def finish(self, job, state: dict) -> None:
        """Records and the metric: mean reward per step over the last 10 % of the steps."""
        rewards = state["rewards"].T.cpu().numpy()
        job.run.save_records("steps", job.R, rewards=rewards, td_errors=state["td_errors"].T.cpu().numpy())
        if state["state_weights_before"] is not None:
            job.run.save_records(
                "weights",
                job.R,
                state_weights_before=state["state_weights_before"].numpy(),
                state_weights_after=job.actor.state_weights().cpu().numpy(),
            )
        last = max(1, self.T // 10)
        # in float64, as final_metrics: the same sum on any CPU
        job.metrics["reward_per_step_last10pct"] = rewards[:, -last:].mean(1, dtype=np.float64).tolist()
        job.count_agent_steps(self.T * job.R, state["actor_time"])
