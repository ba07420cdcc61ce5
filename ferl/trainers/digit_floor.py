"""Chapter 3: the FERL actor on the digit floor (§3.5), all runs of the batch at once.

    test phase (before) → online SARSA(0) / Q(0) / expected-SARSA training → test phase (after)

One training step for every run:  observe s' → F(s', ·) for all actions → sample a' (Eq. 3.11)
→ δ = r − γ F(s', a') + F(s, a) → θ ← θ + α δ (−∂F/∂θ) (Eq. 3.10).  F(s', a') and its hidden
inputs are kept for the next step, so no free energy is computed twice.  ``td_steps`` runs a
chunk of such steps on random numbers drawn beforehand; with ``compile=true`` it is one
``torch.compile``d graph, so Python and per-op overhead is paid once per chunk, not per step,
and on a CPU the chunk runs for one group of runs after another (``td_steps_by_groups``).
With ``trainer.prefetch`` > 0 the random numbers of that many chunks ahead are drawn on a second
thread while a chunk runs: the same draws from the same generator in the same order, so the
results do not change (a chunk itself draws nothing unless actions are Gibbs-sampled, which turns
prefetching off).
"""
import math
import sys
import time
from collections import deque
from contextlib import contextmanager, nullcontext
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
import torch
from hydra.utils import instantiate
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from ferl.evaluation import evaluate_floor, floor_test_images, greedy_accuracy
from ferl.guard import DivergenceGuard
from ferl.random_blocks import Blocks, steps_per_block
from ferl.run_dir import CheckpointTimer, RunDir, StopRequest
from ferl.tb_logging import as_images, flat_config, log_embedding, log_hparams, log_weights, tile, weight_images

hparams = flat_config  # the flattened config of the HParams tab (ferl.tb_logging)
ACTION_NAMES = ("N", "E", "S", "W")
MAX_CHUNK = 16  # steps per call of td_steps (a divisor of the logging and checkpoint intervals)
# Prefetching pays from a few tens of runs on (compile=true, agent-steps/s drawn in turn → ahead:
# 100 runs 157 k → 225–300 k, 30 runs 162–190 k → 230–257 k); at 10 runs it gains nothing and varies
# (160 k → 141–169 k), and a single run's chunk is too short to hide the thread handoff (48 k → 30 k).
PREFETCH_MIN_RUNS = 30
# How long a thread holds the GIL while the other waits for it: at Python's 5 ms default, chunks of
# 10 and 30 runs (1–3 ms) waited for it more than prefetching saved (10 runs: 156 k → 119–128 k
# agent-steps/s; 30 runs, one chunk ahead: 162 k → 135 k).
SWITCH_INTERVAL_S = 2e-4
EMBEDDED_PER_CLASS = 100  # test digits per class in the projector (TensorBoard tags: docs/records.md)


def pick(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Entries of the chosen actions on the online path: x (R, 1, nA, ...) at a (R, 1) → (R, 1, ...)."""
    flat = x.reshape(-1, *x.shape[3:]) if x.dim() > 3 else x.reshape(-1)
    index = a.squeeze(1) + torch.arange(0, flat.shape[0], x.shape[2], device=a.device)
    return flat.index_select(0, index).unsqueeze(1)


def td_steps(actor, env, generator, s, a, F_sa, x_sa, alive, lrs, betas, uniforms, idx, values, transport):
    """len(lrs) online TD steps of every run (§3.2); step k uses α = lrs[k], β = betas[k], the
    action uniforms (R, 1, 1) and the environment's noise and transport draws of index k (Gibbs
    action selection draws from ``generator`` instead, and is not compiled).

    s (R, 1, S), a (R, 1), F_sa (R, 1), x_sa (R, 1, H): the state, action, its free energy and
    hidden input before the chunk; returns them after it, with rewards and TD errors (K, R).
    Runs with ``alive`` False (R, 1) keep their parameters (the divergence guard).
    """
    rewards, deltas = [], []
    for k in range(lrs.shape[0]):
        obs, r = env.step_with(a.squeeze(1), idx[k], values[k], transport[k])
        s_next = obs.unsqueeze(1)
        F_next, x_next = actor.evaluate(s_next)
        a_next = actor.select(s_next, F_next, betas[k], generator, uniforms[k])
        delta = actor.td_error(r.unsqueeze(1), F_sa, F_next, a_next, betas[k])
        F_sa, x_sa = actor.learn(s, a, x_sa, torch.where(alive, delta, 0.0), lrs[k], s_next, a_next,
                                 pick(F_next, a_next), pick(x_next, a_next))
        rewards.append(r)
        deltas.append(delta.squeeze(1))
        s, a = s_next, a_next
    return s, a, F_sa, x_sa, torch.stack(rewards), torch.stack(deltas)


def td_steps_by_groups(steps, groups: list[slice]):
    """``steps`` (td_steps' signature) for one group of runs after another: temporal cache
    blocking. A group's weights stay in the CPU's caches for the whole chunk instead of every
    step streaming all runs' weights from L3. Each group gets views of its runs (actor.runs,
    env.runs, slices of the per-run arguments), so its updates land in the whole batch; runs are
    independent, so the grouping does not change what a run computes."""
    def by_groups(actor, env, generator, s, a, F_sa, x_sa, alive, lrs, betas, uniforms, idx, values, transport):
        parts = [steps(actor.runs(g), env.runs(g), generator, s[g], a[g], F_sa[g], x_sa[g], alive[g], lrs, betas,
                       uniforms[:, g], idx[:, g], values[:, g], transport[:, g]) for g in groups]
        # s, a, F_sa, x_sa carry the runs first, rewards and TD errors (K, R) second
        return tuple(torch.cat(outs, 0 if i < 4 else 1) for i, outs in enumerate(zip(*parts)))
    return by_groups


def compiled_td_steps(n_runs: int, group_runs: int, device: torch.device):
    """td_steps as one torch.compiled graph per chunk; on a CPU with its kernels called from C++
    (no Python between the steps) and run by groups of ``group_runs`` runs (a smaller last group
    compiles a second graph). fullgraph: a graph break would silently bring back per-op overhead."""
    if device.type != "cpu":
        return torch.compile(td_steps, fullgraph=True, dynamic=False)
    steps = torch.compile(td_steps, fullgraph=True, dynamic=False, options={"cpp_wrapper": True})
    if n_runs <= group_runs:
        return steps
    return td_steps_by_groups(steps, [slice(r, min(r + group_runs, n_runs)) for r in range(0, n_runs, group_runs)])


def chunk_length(steps: int, *intervals: int) -> int:
    """The longest chunk ≤ MAX_CHUNK that divides the run length and every interval, so logging
    and periodic checkpoints fall on chunk ends."""
    return math.gcd(MAX_CHUNK, steps, *intervals)


@contextmanager
def switch_interval(seconds: float):
    """Python's GIL switch interval set to ``seconds`` inside the block."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(seconds)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def done_future(value) -> Future:
    """A future that already holds ``value``."""
    future = Future()
    future.set_result(value)
    return future


def json_values(x: np.ndarray) -> list:
    """Per-run values for summary.json; NaN (no optimal action to score, e.g. without reward) → null."""
    return [None if np.isnan(v) else float(v) for v in x]


class FloorTraining:
    """Everything one digit-floor run batch needs, built from the composed config."""

    def __init__(self, cfg, run: RunDir, device: torch.device):
        self.cfg, self.run, self.device = cfg, run, device
        self.R, self.T = cfg.n_runs, cfg.trainer.steps
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        self.data = instantiate(cfg.data).load()
        self.env = instantiate(cfg.env, n_runs=self.R, data=self.data, generator=self.generator, device=device)
        self.actor = instantiate(cfg.actor, n_runs=self.R, n_state=self.env.observation_size,
                                 n_actions=self.env.n_actions, seed=cfg.seed).to(device)
        self.test_images = floor_test_images(self.env.classes, self.data, cfg.trainer.test_per_class, self.generator)
        self.action_uniforms = Blocks(
            lambda steps: (torch.rand(steps, self.R, 1, 1, generator=self.generator, device=device),),
            steps_per_block(self.R))
        self.guard = DivergenceGuard(self.R, cfg.trainer.divergence_limit,
                                     [cfg.seed + r for r in range(self.R)], device)
        self.chunk = chunk_length(self.T, cfg.trainer.log_every, cfg.trainer.checkpoint_every)
        self.td_steps = td_steps
        if cfg.compile:
            # hidden-major weights: the compiled step's Wᵀs and rank-1 update (Eq. 3.10a) then both
            # run along the contiguous visible axis, which inductor vectorises and fuses into one
            # pass over W (eager's bmm is faster on the default layout, so eager keeps it)
            self.actor.W_sh = self.actor.W_sh.transpose(1, 2).contiguous().transpose(1, 2)
            self.td_steps = compiled_td_steps(self.R, cfg.trainer.compile_group_runs, device)
        # chunks of random numbers drawn ahead on a second thread; not with Gibbs action selection,
        # which draws from the generator inside the chunk, nor for batches too small to pay
        drawn_ahead = self.actor.action_selection != "gibbs" and self.R >= PREFETCH_MIN_RUNS
        self.prefetch = cfg.trainer.prefetch if drawn_ahead else 0

    def chunk_inputs(self) -> tuple:
        """The random numbers of one chunk: action uniforms, noisy pixels and values, transports."""
        return (*self.action_uniforms.take(self.chunk), *self.env.noise_blocks.take(self.chunk))

    def test_phase(self) -> dict:
        t = self.cfg.trainer
        return evaluate_floor(self.actor, self.test_images, t.test_noise_levels, self.cfg.env.noise,
                              self.actor.inverse_temperature(1.0), self.generator)

    def fresh_state(self) -> dict:
        """State at step 0: test responses before training, initial weights, first action."""
        before = self.test_phase()
        s = self.env.reset().unsqueeze(1)
        F, x = self.actor.evaluate(s)
        a = self.actor.select(s, F, self.actor.inverse_temperature(0.0), self.generator, *self.action_uniforms.next())
        return {"step": 0, "before": before, "W_sh_before": self.actor.W_sh.cpu().clone(),
                "s": s, "a": a, "F_sa": pick(F, a), "x_sa": pick(x, a),
                "rewards": torch.zeros(self.T, self.R, device=self.device),
                "td_errors": torch.zeros(self.T, self.R, device=self.device), "actor_time": 0.0,
                "checked": 0}  # steps whose TD errors the divergence guard has seen

    def checkpoint(self, state: dict, writer: SummaryWriter) -> None:
        self.run.save_checkpoint({**state, "actor": self.actor.state_dict(), "env": self.env.state_dict(),
                                  "action_uniforms": self.action_uniforms.state_dict(),
                                  "guard": self.guard.state_dict(), "generator": self.generator.get_state()},
                                 writer)

    def restore(self, saved: dict) -> dict:
        self.actor.load_state_dict(saved.pop("actor"))
        self.env.load_state_dict(saved.pop("env"))
        self.action_uniforms.load_state_dict(saved.pop("action_uniforms"), self.device)
        self.guard.load_state_dict(saved.pop("guard"))
        self.generator.set_state(saved.pop("generator"))
        saved["inputs"] = [tuple(x.to(self.device) for x in inputs) for inputs in saved.get("inputs", ())]
        return {k: v.to(self.device) if torch.is_tensor(v) and k != "W_sh_before" else v for k, v in saved.items()}

    def train(self, state: dict, writer: SummaryWriter, stop: StopRequest) -> dict:
        """The online TD loop of §3.2 from state["step"] to T; returns the final state."""
        actor, env, T = self.actor, self.env, self.T
        t_cfg = self.cfg.trainer
        s, a, F_sa, x_sa = state["s"], state["a"], state["F_sa"], state["x_sa"]
        rewards, td_errors = state["rewards"], state["td_errors"]
        clock = CheckpointTimer(t_cfg.checkpoint_minutes)
        bar = tqdm(total=T, initial=state["step"], desc="actor", unit="step", mininterval=1.0, dynamic_ncols=True)
        started = time.perf_counter()
        # random inputs of the next chunks, in draw order; a checkpoint's were drawn before the
        # generator state it saved
        pending = deque(done_future(inputs) for inputs in state.pop("inputs", ()))
        drawn_to = state["step"] + self.chunk * len(pending)  # the first step not yet drawn for
        with ThreadPoolExecutor(1, thread_name_prefix="ferl-random") as worker, \
                switch_interval(SWITCH_INTERVAL_S) if self.prefetch else nullcontext():
            for t in range(state["step"], T, self.chunk):
                while drawn_to < min(T, t + (self.prefetch + 1) * self.chunk):
                    pending.append(worker.submit(self.chunk_inputs) if self.prefetch else done_future(self.chunk_inputs()))
                    drawn_to += self.chunk
                inputs = pending.popleft().result()
                progress = [(t + k) / T for k in range(self.chunk)]
                lrs = torch.tensor([actor.learning_rate(p) for p in progress], device=self.device)
                betas = torch.tensor([actor.inverse_temperature(p) for p in progress], device=self.device)
                s, a, F_sa, x_sa, r, delta = self.td_steps(
                    actor, env, self.generator, s, a, F_sa, x_sa, self.guard.alive, lrs, betas, *inputs)
                rewards[t:t + self.chunk], td_errors[t:t + self.chunk] = r, delta
                lr, beta = float(lrs[-1]), float(betas[-1])

                done = t + self.chunk
                if done % t_cfg.log_every == 0 or done == T:
                    self.guard.check(td_errors[state["checked"]:done], state["checked"])
                    state["checked"] = done
                    self.log_progress(writer, rewards, td_errors, done, lr, beta)
                    bar.set_postfix(reward_ma100=f"{rewards[max(0, done - 100):done].mean():.2f}", refresh=False)
                    bar.update(done - bar.n)
                if done % t_cfg.checkpoint_every == 0 or stop.requested or done == T or clock.due():
                    state.update(step=done, s=s, a=a, F_sa=F_sa, x_sa=x_sa, inputs=[f.result() for f in pending],
                                 actor_time=state["actor_time"] + time.perf_counter() - started)
                    started = time.perf_counter()
                    self.checkpoint(state, writer)
                    del state["inputs"]  # in the checkpoint only
                    if stop.requested:
                        bar.close()
                        raise SystemExit(128 + stop.signal)
        bar.close()
        return state

    def log_progress(self, writer, rewards, td_errors, done, lr, beta) -> None:
        """Fig. 3.4's 100-step moving average (mean and spread over runs), TD error, α, β."""
        window = rewards[max(0, done - 100):done].mean(0)
        recent_td = td_errors[max(0, done - self.cfg.trainer.log_every):done].abs().mean()
        for name, value in {"reward_ma100": window.mean(), "reward_ma100_std": window.std(correction=0),
                            "reward_ma100_min": window.min(), "reward_ma100_max": window.max(),
                            "td_error_abs": recent_td}.items():
            writer.add_scalar(f"actor/{name}", value.item(), done)
        writer.add_scalar("schedule/learning_rate", lr, done)
        writer.add_scalar("schedule/beta", beta, done)

    def log_actor(self, writer, step: int) -> None:
        """Run 0's weights: histograms and the 28 × 28 image→hidden tiles (Fig. 3.5)."""
        log_weights(writer, "actor", self.actor, step)
        writer.add_image("actor/W_sh_images", tile(weight_images(self.actor.W_sh)[:, 0]), step)

    def log_test(self, writer, result: dict, step: int) -> None:
        """Greedy accuracy per test-noise level, mean over runs (Fig. 3.6), before / after training."""
        accuracy = greedy_accuracy(result["greedy_counts"], self.env.class_optimal_action)
        for i, level in enumerate(self.cfg.trainer.test_noise_levels):
            if not np.isnan(accuracy[:, i]).all():
                writer.add_scalar(f"test/greedy_accuracy_{level:g}", float(np.nanmean(accuracy[:, i])), step)

    def log_test_digits(self, writer, after: dict, step: int) -> None:
        """Sample observations (clean test images and the noisy ones the actor was probed with,
        one row per class) and run 0's hidden activations per test digit in the projector."""
        n = min(8, self.test_images.shape[1])
        writer.add_image("test/observations_clean", tile(as_images(self.test_images[:, :n])), step)
        writer.add_image("test/observations_noisy", tile(as_images(after["probe_images"][:, :n])), step)
        C, k = self.test_images.shape[0], min(EMBEDDED_PER_CLASS, self.test_images.shape[1])
        optimal = self.env.class_optimal_action
        greedy = after["probs"][0, :, :k].argmax(-1)  # (C, k): softmax is monotone in −F at β > 0
        log_embedding(writer, "actor/hidden_test_digits", after["hidden"][0, :, :k].reshape(C * k, -1), {
            "class": np.repeat(np.asarray(self.env.classes), k),
            "optimal_action": np.repeat([ACTION_NAMES[a] if a >= 0 else "none" for a in optimal], k),
            "greedy_action": [ACTION_NAMES[a] for a in greedy.reshape(-1)],
        }, step, images=after["probe_images"][:, :k])

    def records_and_summary(self, state: dict, after: dict, wall_time: float) -> dict:
        env, before = self.env, state["before"]
        rewards = state["rewards"].T.cpu().numpy()
        self.run.save_records("floor_train", rewards=rewards, td_errors=state["td_errors"].T.cpu().numpy())
        self.run.save_records("weights", W_sh_before=state["W_sh_before"].numpy(), W_sh_after=self.actor.W_sh.cpu().numpy())
        self.run.save_records(
            "floor_test", noise_levels=np.asarray(self.cfg.trainer.test_noise_levels, dtype=np.float64),
            classes=np.array(env.classes), optimal_action=env.class_optimal_action.astype(np.int64),
            action_names=np.array(["N", "E", "S", "W"]), arrangement=env.arrangement,
            probe_noise=np.float64(self.cfg.env.noise), beta=np.float64(self.actor.inverse_temperature(1.0)),
            clean_images=self.test_images.cpu().numpy().astype(np.float16),
            probe_images=after["probe_images"],
            **{f"{key}_{phase}": result[key] for phase, result in (("before", before), ("after", after))
               for key in ("greedy_counts", "probs", "hidden", "hidden_marginal")})
        levels = [f"{x:g}" for x in self.cfg.trainer.test_noise_levels]
        acc_after = greedy_accuracy(after["greedy_counts"], env.class_optimal_action)
        acc_before = greedy_accuracy(before["greedy_counts"], env.class_optimal_action)
        last = max(1, self.T // 10)
        return {
            "reward_per_step_last10pct": rewards[:, -last:].mean(1).tolist(),
            "greedy_accuracy": {lvl: json_values(acc_after[:, i]) for i, lvl in enumerate(levels)},
            "greedy_accuracy_before": {lvl: json_values(acc_before[:, i]) for i, lvl in enumerate(levels)},
        }


def train_digit_floor(cfg, run: RunDir, device: torch.device) -> dict:
    """Run the whole chapter-3 procedure; returns the summary.json dict."""
    wall_start = time.perf_counter()
    job = FloorTraining(cfg, run, device)
    saved = run.resume() if cfg.resume else None
    state = job.restore(saved) if saved else job.fresh_state()
    with SummaryWriter(run.tb) as writer:
        if state["step"] == 0:  # not again on resume: the interrupted run logged these
            job.log_actor(writer, 0)
            job.log_test(writer, state["before"], 0)
        with StopRequest() as stop:
            state = job.train(state, writer, stop)
        after = job.test_phase()
        metrics = job.records_and_summary(state, after, time.perf_counter() - wall_start)
        job.log_actor(writer, job.T)
        job.log_test(writer, after, job.T)
        job.log_test_digits(writer, after, job.T)
        agent_steps = job.T * job.R
        summary = {
            "experiment": cfg.name, "task": "digit_floor",
            "seeds": [cfg.seed + r for r in range(job.R)],
            "metrics": metrics, "optimal": {"reward_per_step": job.env.optimal_reward_rate},
            "wall_time_s": time.perf_counter() - wall_start,
            "agent_steps_per_s": agent_steps / max(state["actor_time"], 1e-9),
            "diverged": job.guard.report("step"),
        }
        log_hparams(writer, cfg, summary, job.T)
    return summary
