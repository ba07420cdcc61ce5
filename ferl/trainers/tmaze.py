"""Chapters 4–5: predictor–actor agents on the T-maze POMDPs (Algorithm 1, Algorithm 2).

    [ch. 5] train the RBM preprocessor by CD-k; processed observation y = ĥ(y⁽⁰⁾) (§5.2)
    collect N_sample random episodes → balance and split (§4.3.1)
    → train every Elman predictor by BPTT in pattern mode (Eqs. 4.1–4.6; 5.1–5.2), logging the
      Eq. 4.7–4.8 errors (squared error for a scalar reward, Fig. 5.17b)
    → freeze them and train the FERL actor on the state (y_t, m_t of every predictor) by SARSA(0)

Chapter 4 has one joint predictor; chapter 5 an observation and a reward predictor (§5.2), each
with its own memory. All runs of the batch play their episodes in lockstep: episode k of every
run starts together, runs whose episode has ended wait (their TD errors are masked) until the
slowest has finished. The random numbers of an episode (action draws here, reservoir images in
the environment) are drawn for all T_max steps when it starts, so no run's episode length shifts
another run's random stream.
"""
import time

import numpy as np
import torch
import torch.nn.functional as F
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from ferl.guard import DivergenceGuard
from ferl.predictor import PredictorBatch, scaled
from ferl.preprocessor import load_or_fit
from ferl.random_blocks import Blocks, steps_per_block
from ferl.run_dir import CheckpointTimer, RunDir, StopRequest
from ferl.sequences import Episodes, balance_and_split, collect_random_episodes
from ferl.tb_logging import (IMAGE_SIDE, as_images, log_embedding, log_hparams, log_weights, matrix_image, tile,
                              weight_images)
from ferl.trainers.digit_floor import pick
from ferl.validate import ConfigError

PREPROCESSOR_EXTRA_KEYS = ("cache_dir",)  # preprocessor keys that are not constructor arguments
EMBEDDED_JUNCTION_VISITS = 2000  # run 0's last junction visits in the projector (docs/records.md)
# per-episode records of the actor phase (records/episodes.npz), in the order play_episode returns them
OUTCOMES = ("discounted_return", "steps", "terminal_reward", "correct_goal", "td_abs_mean", "condition")


class TMazeTraining:
    def __init__(self, cfg, run: RunDir, device: torch.device):
        self.cfg, self.run, self.device = cfg, run, device
        self.R = cfg.n_runs
        self.generator = torch.Generator(device).manual_seed(cfg.seed)
        self.data = instantiate(cfg.data).load() if cfg.env.get("digit_classes") else None
        self.env = self.make_env(self.R)
        self.preprocessor = self.make_preprocessor()
        n_obs = cfg.preprocessor.n_hidden if self.preprocessor is not None else self.env.observation_size
        self.predictors = {name: instantiate(p, n_runs=self.R, n_obs=n_obs, n_actions=self.env.n_actions,
                                             seed=cfg.seed + 10_000 * i).to(device)
                           for i, (name, p) in enumerate(cfg.predictor.items())}
        n_state = n_obs + sum(p.n_memory for p in cfg.predictor.values())
        self.actor = instantiate(cfg.actor, n_runs=self.R, n_state=n_state, n_actions=self.env.n_actions,
                                 seed=cfg.seed + 100_000).to(device)
        self.gamma = cfg.actor.gamma
        self.table = self.env.observation_table  # (ids, Y), or (R, ids, Y) once processed
        self.guard = DivergenceGuard(self.R, cfg.trainer.divergence_limit,
                                     [cfg.seed + r for r in range(self.R)], device)
        steps = cfg.env.max_steps + 1  # an episode's action draws: a_0 … a_{T_max}
        self.episode_uniforms = Blocks(
            lambda n: (torch.rand(n, steps, self.R, 1, 1, generator=self.generator, device=device),),
            steps_per_block(steps * self.R))

    def make_env(self, n_runs: int):
        extra = {"data": self.data} if self.data is not None else {}
        try:
            return instantiate(self.cfg.env, n_runs=n_runs, generator=self.generator, device=self.device, **extra)
        except InstantiationException as e:  # e.g. a reservoir larger than the data's class pool
            raise ConfigError(str(e.__cause__ or e).splitlines()[0]) from None

    def make_preprocessor(self):
        pcfg = self.cfg.get("preprocessor")
        if pcfg is None:
            return None
        args = {k: v for k, v in OmegaConf.to_container(pcfg, resolve=True).items() if k not in PREPROCESSOR_EXTRA_KEYS}
        return instantiate(args, n_runs=self.R, seed=self.cfg.seed + 200_000).to(self.device)

    # ---- preprocessor (Algorithm 2, first phase) ------------------------------------------------
    def train_preprocessor(self, writer: SummaryWriter) -> dict:
        """CD-k on the MNIST training images (§5.3.2), or the cached result of the same settings;
        the observation table becomes each run's processed observations ĥ (R, ids, N^y)."""
        images = self.data.train_images.to(self.device)
        test = self.data.test_images.to(self.device)
        before = self.preprocessor.reconstruction_error(test)
        # no generator: every run trains on its own stream (seed + r), so the cache key is complete
        history, cached = load_or_fit(self.preprocessor, images, None, self.cfg.preprocessor.cache_dir,
                                      {"data": OmegaConf.to_container(self.cfg.data, resolve=True)}, writer)
        sweeps = np.asarray(history).shape[1]
        if cached:  # the fit's own logging happened in the run that trained it
            for sweep, value in enumerate(np.asarray(history).mean(0), 1):
                writer.add_scalar("preprocessor/reconstruction_error", float(value), sweep)
            if self.preprocessor.W.shape[1] == IMAGE_SIDE ** 2:
                writer.add_images("preprocessor/filters", weight_images(self.preprocessor.W), sweeps)
        after = self.preprocessor.reconstruction_error(test)
        self.log_preprocessor(writer, test, before, after, sweeps)
        with torch.no_grad():
            self.table = self.preprocessor.transform(self.env.observation_table)
        return {"reconstruction_error": np.asarray(history), "test_error_before": before.cpu().numpy(),
                "test_error_after": after.cpu().numpy(), "cached": np.bool_(cached),
                "raw_observations": self.env.observation_table.cpu().numpy().astype(np.float16),
                "processed_observations": self.table.cpu().numpy().astype(np.float16)}

    def log_preprocessor(self, writer, test: torch.Tensor, before, after, sweeps: int) -> None:
        """Held-out reconstruction error before / after (mean over runs), run 0's weights, and
        its reconstructions σ(W ĥ + b_v) of one test image per digit class (row 2) under the
        images (row 1)."""
        writer.add_scalar("preprocessor/test_reconstruction_error", float(before.mean()), 0)
        writer.add_scalar("preprocessor/test_reconstruction_error", float(after.mean()), sweeps)
        log_weights(writer, "preprocessor", self.preprocessor, sweeps)
        if test.shape[1] != IMAGE_SIDE ** 2:
            return
        labels = self.data.test_labels.cpu()
        first = [int(torch.nonzero(labels == c)[0]) for c in labels.unique().tolist()][:10]
        images = test[first]
        with torch.no_grad():
            recon = self.preprocessor.visible_given(self.preprocessor.transform(images))[0]
        writer.add_image("preprocessor/reconstructions", tile(torch.stack([as_images(images), as_images(recon)])), sweeps)

    def log_observations(self, writer) -> None:
        """What the agent observes: up to 8 images of every observation's reservoir (one row
        per observation of the environment's table), or the table of bit codes itself."""
        table, names = self.env.observation_table.float().cpu(), self.env.observation_names
        if table.shape[1] == IMAGE_SIDE ** 2:
            per_name = table.view(len(names), -1, table.shape[1])
            writer.add_image("env/observations", tile(as_images(per_name[:, :8])), 0)
        else:
            writer.add_image("env/observations", matrix_image(table), 0)

    def log_collect(self, writer, data: dict) -> None:
        writer.add_scalar("collect/train_sequences", data["train"].lengths.shape[1], 0)
        writer.add_scalar("collect/test_sequences", data["test"].lengths.shape[1], 0)
        writer.add_scalar("collect/train_per_length", data["n_train"], 0)

    # ---- predictor data and training --------------------------------------------------------
    def lookup(self, ids: torch.Tensor) -> torch.Tensor:
        """(Processed) observation vectors of valid observation ids (R, …): the online step."""
        if self.table.dim() == 2:
            return self.table[ids]
        runs = torch.arange(self.R, device=self.device).view(-1, *([1] * (ids.dim() - 1)))
        return self.table[runs, ids]

    def observations(self, ids: torch.Tensor) -> torch.Tensor:
        """As ``lookup`` for padded episodes: the padding id −1 gives zeros."""
        return torch.where((ids >= 0).unsqueeze(-1), self.lookup(ids.clamp(min=0)), 0.0)

    def tensors(self, ep: Episodes, predictor):
        """Episodes → predictor inputs y (R,B,T+1,Y), a (R,B,T,A), r targets (R,B,T+1,·) of
        ``predictor`` (None without one), lengths."""
        y = self.observations(ep.obs)
        a = F.one_hot(ep.actions, self.env.n_actions).float()
        r = predictor.reward_targets(self.env, ep.rewards) if predictor is not None else None
        return y, a, r, ep.lengths

    def collect(self) -> dict:
        t = self.cfg.trainer
        copies = max(1, min(t.n_sample, t.collect_batch // self.R))
        env = self.make_env(self.R * copies)
        episodes = collect_random_episodes(env, t.n_sample, self.R, self.generator)
        train, test, (n_train, n_test) = balance_and_split(
            episodes, self.env.optimal_steps, self.cfg.env.max_steps, t.train_fraction, self.generator)
        return {"train": train, "test": test, "n_train": n_train, "n_test": n_test}

    def prediction_errors(self, tensors: tuple, predictor) -> np.ndarray:
        """(R, nT, Tmax+1) Eq. (4.7): mean over the sequences of each length of Eq. (4.8) per step;
        ``tensors`` (y, a, r, lengths) of a data split (``tensors``)."""
        lengths = tensors[3]
        err = predictor.prediction_errors(*tensors)  # (R, B, Tmax+1), NaN on padding
        lengths_all = range(self.env.optimal_steps, self.cfg.env.max_steps + 1)
        out = [torch.nanmean(torch.where((lengths == T).unsqueeze(-1), err, torch.nan), dim=1) for T in lengths_all]
        return torch.stack(out, 1).cpu().numpy().astype(np.float32)

    def train_predictors(self, data: dict, writer: SummaryWriter, progress: dict | None = None,
                         stop: StopRequest | None = None) -> dict:
        """Every predictor on the same episodes, each in its own shuffled order per epoch; those
        that share the form of the memory train as one batch (``PredictorBatch``). A predictor
        whose phase a checkpoint lists as done is not trained again."""
        progress = progress if progress is not None else {"done": []}
        stop = stop if stop is not None else StopRequest()
        records = progress.setdefault("predictor_records", {})
        groups = {}
        for name, p in self.predictors.items():
            groups.setdefault(p.batch_key, []).append(name)
        for names in groups.values():
            if any(f"predictor_{name}" not in progress["done"] for name in names):
                records |= self.train_predictor_group(names, data, writer, progress, stop)
                progress["done"] += [f"predictor_{name}" for name in names]
                self.checkpoint(progress, writer, stop)
        return records

    def train_predictor_group(self, names: list, data: dict, writer: SummaryWriter,
                              progress: dict, stop: StopRequest) -> dict:
        """Pattern-mode BPTT of the named predictors for N_epoch epochs, from the epoch a
        checkpoint left them at; a checkpoint every ``trainer.checkpoint_every_epochs`` epochs
        and on SIGINT/SIGTERM."""
        t = self.cfg.trainer
        train = data["train"]
        members = [self.predictors[name] for name in names]
        # the training set proper: lengths T_min … T_min + L_training − 1; balancing laid the
        # lengths out in the same blocks in every run, so run 0's positions hold for all
        trainable = train.lengths[0] <= self.env.optimal_steps + t.l_training - 1
        fit = train.select(torch.nonzero(trainable).squeeze(1).expand(self.R, -1))
        y, a, _, lengths = self.tensors(fit, None)
        batch = PredictorBatch(members, y, a, [p.reward_targets(self.env, fit.rewards) for p in members], lengths)
        splits = {(name, s): self.tensors(data[s], p) for name, p in zip(names, members) for s in ("train", "test")}
        partial = progress.get("predictor_partial") or {}
        if partial.get("names") == names:
            errors, epochs, start = partial["errors"], partial["epochs"], partial["epoch"]
        else:
            errors = {name: {s: [self.prediction_errors(splits[name, s], p)] for s in ("train", "test")}
                      for name, p in zip(names, members)}
            epochs, start = [0], 0
            for name, p in zip(names, members):
                log_weights(writer, f"predictor_{name}", p, 0)
        clock = CheckpointTimer(t.checkpoint_minutes)
        for epoch in (bar := tqdm(range(start + 1, t.n_epoch + 1), desc=f"predictor {'+'.join(names)}",
                                  unit="epoch", initial=start, total=t.n_epoch, mininterval=1.0)):
            orders = [torch.rand(self.R, y.shape[1], generator=self.generator, device=self.device).argsort(1)
                      for _ in members]
            batch.train_epoch(orders)
            if epoch % t.error_every == 0 or epoch == t.n_epoch:
                epochs.append(epoch)
                for name, p in zip(names, members):
                    self.log_prediction_errors(name, p, errors[name], splits, writer, epoch)
                bar.set_postfix(error_test=" ".join(f"{np.nanmean(errors[n]['test'][-1]):.4f}" for n in names), refresh=False)
            if (epoch % t.checkpoint_every_epochs == 0 or stop.requested or clock.due()) and epoch < t.n_epoch:
                progress["predictor_partial"] = {"names": names, "epoch": epoch, "errors": errors, "epochs": epochs}
                self.checkpoint(progress, writer, stop)
        progress["predictor_partial"] = None
        lengths_all = np.arange(self.env.optimal_steps, self.cfg.env.max_steps + 1)
        records = {}
        for name, p in zip(names, members):
            log_weights(writer, f"predictor_{name}", p, t.n_epoch)
            records |= {f"{name}_lengths": lengths_all, f"{name}_epochs": np.asarray(epochs),
                        **{f"{name}_error_{s}": np.stack(errors[name][s], 1) for s in ("train", "test")}}
        return records

    def log_prediction_errors(self, name: str, predictor, errors: dict, splits: dict, writer, epoch: int) -> None:
        """Append the Eq. 4.7 errors of both splits to ``errors`` and log them (mean, and test per T)."""
        for split in ("train", "test"):
            errors[split].append(self.prediction_errors(splits[name, split], predictor))
            writer.add_scalar(f"predictor_{name}/error_{split}", float(np.nanmean(errors[split][-1])), epoch)
        for T, value in zip(range(self.env.optimal_steps, self.cfg.env.max_steps + 1),
                            np.nanmean(errors["test"][-1], axis=(0, 2))):
            writer.add_scalar(f"predictor_{name}/error_test_T{T}", float(value), epoch)

    # ---- checkpoints (CONTRACT §2: interruption and resume) ---------------------------------------
    def checkpoint(self, progress: dict, writer: SummaryWriter, stop: StopRequest) -> None:
        """Write everything a resumed run needs (atomically); exit if a signal asked to stop."""
        self.run.save_checkpoint({
            "progress": progress, "generator": self.generator.get_state(),
            "predictors": {n: p.state_dict() for n, p in self.predictors.items()},
            "preprocessor": self.preprocessor.state_dict() if self.preprocessor is not None else None,
            "actor": self.actor.state_dict(), "guard": self.guard.state_dict(),
            "episode_uniforms": self.episode_uniforms.state_dict()}, writer)
        if stop.requested:
            raise SystemExit(128 + stop.signal)

    def finish_phase(self, progress: dict, phase: str, writer: SummaryWriter, stop: StopRequest) -> None:
        progress["done"].append(phase)
        self.checkpoint(progress, writer, stop)

    def restore(self, saved: dict) -> dict:
        """Parameters and RNG state of a checkpoint; returns its progress (finished phases, data,
        records so far)."""
        self.generator.set_state(saved["generator"])
        for name, p in self.predictors.items():
            p.load_state_dict(saved["predictors"][name])
        self.actor.load_state_dict(saved["actor"])
        self.guard.load_state_dict(saved["guard"])
        self.episode_uniforms.load_state_dict(saved["episode_uniforms"], self.device)
        if self.preprocessor is not None and saved["preprocessor"] is not None:
            self.preprocessor.load_state_dict(saved["preprocessor"])
            if "preprocessor" in saved["progress"]["done"]:
                with torch.no_grad():
                    self.table = self.preprocessor.transform(self.env.observation_table)
        return saved["progress"]

    # ---- actor phase ----------------------------------------------------------------------------
    def fresh_actor_state(self) -> dict:
        """Records of the actor phase before its first episode."""
        R, N, T_max = self.R, self.cfg.trainer.n_episodes, self.cfg.env.max_steps
        records = {k: np.zeros((R, N), dtype=dt) for k, dt in (
            ("discounted_return", np.float32), ("steps", np.int64), ("terminal_reward", np.float32),
            ("correct_goal", bool), ("td_abs_mean", np.float32), ("condition", np.int64))}
        n_sampled = len(range(0, N, self.cfg.trainer.td_sample_every))
        return {"episode": 0, "records": records, "junction": [], "active_time": 0.0, "agent_steps": 0,
                "td_sampled": np.full((R, n_sampled, T_max), np.nan, dtype=np.float32)}

    def train_actor(self, writer: SummaryWriter, stop: StopRequest, progress: dict | None = None) -> dict:
        """SARSA(0) episodes from where a checkpoint left them (``progress["actor_partial"]``);
        a checkpoint every ``trainer.checkpoint_every`` episodes and on SIGINT/SIGTERM."""
        cfg, R = self.cfg, self.R
        N, T_max = cfg.trainer.n_episodes, cfg.env.max_steps
        progress = progress if progress is not None else {"done": []}
        if progress.get("actor_partial") is None:
            self.log_actor(writer, 0)
        state = progress.get("actor_partial") or self.fresh_actor_state()
        records, td_sampled, junction = state["records"], state["td_sampled"], state["junction"]
        active_time, agent_steps = state["active_time"], state["agent_steps"]
        sampled = list(range(0, N, cfg.trainer.td_sample_every))
        self.freeze_predictors()
        clock = CheckpointTimer(cfg.trainer.checkpoint_minutes)
        bar = tqdm(range(state["episode"], N), desc="actor", unit="episode", initial=state["episode"],
                   total=N, mininterval=1.0)
        for k in bar:
            started = time.perf_counter()
            lr, beta = self.actor.learning_rate(k / N), self.actor.inverse_temperature(k / N)
            episode = self.play_episode(k, lr, beta)
            active_time += time.perf_counter() - started
            outcome = episode["outcome"].cpu().numpy()  # one host copy per episode
            for i, key in enumerate(OUTCOMES):
                records[key][:, k] = outcome[i]
            agent_steps += int(outcome[OUTCOMES.index("steps")].sum())
            if episode["junction"] is not None:
                junction.append(episode["junction"])
            if k % cfg.trainer.td_sample_every == 0:
                td = episode["td"].T.cpu().numpy()
                td_sampled[:, k // cfg.trainer.td_sample_every, : td.shape[1]] = td
            if (k + 1) % cfg.trainer.log_every == 0 or k + 1 == N:
                checked = k + 1 - (k % cfg.trainer.log_every + 1)  # first episode not yet checked
                self.guard.check(torch.as_tensor(records["td_abs_mean"][:, checked:k + 1].T), checked, "episode")
            if (k + 1) % cfg.trainer.log_every == 0:
                self.log_episodes(writer, records, k + 1, lr, beta)
                bar.set_postfix(return_ma200=f"{records['discounted_return'][:, max(0, k - 199):k + 1].mean():.3f}",
                                correct_ma200=f"{records['correct_goal'][:, max(0, k - 199):k + 1].mean():.2f}", refresh=False)
            if ((k + 1) % cfg.trainer.checkpoint_every == 0 or stop.requested or clock.due()) and k + 1 < N:
                junction = [concat_records(junction)] if junction else []
                progress["actor_partial"] = {"episode": k + 1, "records": records, "td_sampled": td_sampled,
                                             "junction": junction, "active_time": active_time,
                                             "agent_steps": agent_steps}
                self.checkpoint(progress, writer, stop)
        bar.close()
        progress["actor_partial"] = None
        self.log_actor(writer, N)
        junction_arrays = {key: v.numpy() for key, v in concat_records(junction).items()} if junction else {}
        if junction_arrays:
            junction_arrays["steps_to_goal"] = records["steps"][junction_arrays["run"], junction_arrays["episode"]]
        episodes = {**records, "td_sampled": td_sampled, "td_sampled_episodes": np.asarray(sampled),
                    "gamma": np.float64(self.gamma), "optimal_return": np.float64(self.optimal_return),
                    "optimal_steps": np.float64(self.env.optimal_steps)}
        return {"episodes": episodes, "junction": junction_arrays, "actor_time": active_time,
                "agent_steps": agent_steps}

    def freeze_predictors(self) -> None:
        """The frozen predictors' drive tables (``ElmanPredictor.drive_table``), the actor's
        observation rows (times ``trainer.actor_obs_scale``) and the row offsets that address
        run r's part of them."""
        ids = self.env.observation_table.shape[0]
        runs = torch.arange(self.R, device=self.device)
        self.drive_tables = [p.drive_table(self.table).flatten(0, 1) for p in self.predictors.values()]
        self.drive_offsets = runs * (ids * self.env.n_actions)
        self.obs_rows = scaled(self.table.reshape(-1, self.table.shape[-1]), self.cfg.trainer.actor_obs_scale)
        self.obs_offsets = runs * ids if self.table.dim() == 3 else None
        self.initial_memories = [p.initial()[0] for p in self.predictors.values()]
        self.discounts = self.gamma ** torch.arange(self.cfg.env.max_steps, device=self.device, dtype=torch.float32)

    def state(self, obs_id: torch.Tensor, memories: list) -> torch.Tensor:
        """The actor's state (R, 1, S): the (processed) observation, then every predictor's memory."""
        rows = obs_id if self.obs_offsets is None else obs_id + self.obs_offsets
        return torch.cat([self.obs_rows.index_select(0, rows), *memories], 1).unsqueeze(1)

    def play_episode(self, k: int, lr: float, beta: float) -> dict:
        """Episode k of every run, in lockstep, with SARSA(0) updates at every step (§4.2):
        observe → memories m_t (Eq. 4.3) → F(s', ·) for every action → a' by Eq. (3.11) →
        δ = r − γ F(s', a') + F(s, a) → θ ← θ + α δ (−∂F/∂θ) (Eq. 3.10). Runs whose episode has
        ended wait with δ = 0. Returns the outcome (len(OUTCOMES), R), the TD errors (steps, R),
        NaN where a run had ended, and the T-junction visits (or None)."""
        env, actor = self.env, self.actor
        env.reset()
        (uniform,) = self.episode_uniforms.next()  # (T_max + 1, R, 1, 1)
        m = self.initial_memories
        s = self.state(env.obs_id, m)
        F_all, x = actor.evaluate(s)
        a = actor.select(s, F_all, beta, self.generator, uniform[0])
        F_sa, x_sa = pick(F_all, a), pick(x, a)
        rewards, deltas, visits = [], [], []
        for t in range(self.cfg.env.max_steps):
            active = ~env.done
            visits.append((env.at_junction & active, active, m, s, x_sa))
            rows = torch.add(a.squeeze(1), env.obs_id, alpha=env.n_actions) + self.drive_offsets  # (y_{t−1}, a_{t−1})
            r, terminated, _ = env.advance(a.squeeze(1))
            m = [p.online_memory(table, rows, mem)
                 for p, table, mem in zip(self.predictors.values(), self.drive_tables, m)]
            s_next = self.state(env.obs_id, m)
            F_next, x_next = actor.evaluate(s_next)
            a_next = actor.select(s_next, F_next, beta, self.generator, uniform[t + 1])
            delta = actor.td_error(r.unsqueeze(1), F_sa, F_next, a_next, beta, (terminated | ~active).unsqueeze(1))
            delta = torch.where(active.unsqueeze(1), delta, 0.0)
            F_sa, x_sa = actor.learn(s, a, x_sa, self.guard.mask(delta), lr, s_next, a_next,
                                     pick(F_next, a_next), pick(x_next, a_next))
            rewards.append(r)
            deltas.append(delta.squeeze(1))
            s, a = s_next, a_next
            if bool(env.done.all()):
                break
        rewards, deltas = torch.stack(rewards), torch.stack(deltas)  # (steps, R)
        actives = torch.stack([v[1] for v in visits])
        steps = env.t
        outcome = torch.stack([
            self.discounts[:len(rewards)] @ rewards,  # discounted return (done runs got r = 0)
            steps.float(), rewards.gather(0, (steps - 1).unsqueeze(0)).squeeze(0),  # terminal reward
            env.correct.float(), deltas.abs().sum(0) / steps.clamp(min=1), env.condition.float()])
        return {"outcome": outcome, "td": torch.where(actives, deltas, torch.nan),
                "junction": self.junction_visits(k, visits)}

    def junction_visits(self, k: int, visits: list) -> dict | None:
        """Activations at every T-junction visit of episode k after the action there was
        selected (Figs. 4.14–4.19): memories, actor state and hidden nodes, with the condition."""
        env = self.env
        step, run = torch.stack([v[0] for v in visits]).nonzero(as_tuple=True)
        if len(run) == 0:
            return None
        gather = lambda xs: torch.stack(xs)[step, run]  # noqa: E731
        return {"run": run.cpu(), "episode": torch.full_like(run, k).cpu(), "step": step.cpu(),
                "condition": env.condition[run].cpu(), "initial_signal": env.initial_signal[run].cpu(),
                "junction_signal": env.junction_signal[run].cpu(),
                **{f"memory_{name}": gather([v[2][i] for v in visits]).half().cpu()
                   for i, name in enumerate(self.predictors)},
                "state": gather([v[3][:, 0] for v in visits]).half().cpu(),
                "hidden": torch.sigmoid(gather([v[4][:, 0] for v in visits])).half().cpu()}

    @property
    def optimal_return(self) -> float:
        return self.env.optimal_discounted_return(self.gamma)

    def log_actor(self, writer, step: int) -> None:
        """Run 0's weights: histograms, W_sh as a (state nodes × hidden) image and, where the
        observation is an unprocessed image, its 784 rows as 28 × 28 tiles."""
        log_weights(writer, "actor", self.actor, step)
        W = self.actor.W_sh
        writer.add_image("actor/W_sh_matrix", matrix_image(W[0]), step)
        if self.preprocessor is None and self.env.observation_size == IMAGE_SIDE ** 2:
            writer.add_image("actor/W_sh_images", tile(weight_images(W[:, :IMAGE_SIDE ** 2])[:, 0]), step)

    def log_junction(self, writer, junction: dict, episodes: dict, step: int) -> None:
        """Run 0's actor hidden activations at its last T-junction visits in the projector,
        labelled with the episode's condition and outcome (Figs. 4.14–4.19)."""
        visits = np.flatnonzero(junction["run"] == 0)[-EMBEDDED_JUNCTION_VISITS:] if junction else []
        if len(visits) == 0:
            return
        episode = junction["episode"][visits]
        log_embedding(writer, "actor/hidden_at_junction", junction["hidden"][visits], {
            **{key: junction[key][visits] for key in ("condition", "initial_signal", "junction_signal")},
            "episode": episode, "steps_to_goal": junction["steps_to_goal"][visits],
            "correct_goal": episodes["correct_goal"][0, episode].astype(int)}, step)

    def log_episodes(self, writer, records, done: int, lr: float, beta: float) -> None:
        """200-episode moving averages, mean over runs (Figs. 4.6–4.8, 4.11–4.13)."""
        window = slice(max(0, done - 200), done)
        for name in ("discounted_return", "steps", "terminal_reward", "td_abs_mean", "correct_goal"):
            writer.add_scalar(f"actor/{name}_ma200", float(records[name][:, window].mean()), done)
        writer.add_scalar("schedule/learning_rate", lr, done)
        writer.add_scalar("schedule/beta", beta, done)


def train_tmaze(cfg, run: RunDir, device: torch.device) -> dict:
    """Algorithm 1 / 2 phase by phase, each skipped when a resumed checkpoint lists it as done;
    returns the summary.json dict."""
    wall_start = time.perf_counter()
    job = TMazeTraining(cfg, run, device)
    saved = run.resume() if cfg.resume else None
    progress = job.restore(saved) if saved else {"done": []}
    with SummaryWriter(run.tb) as writer, StopRequest() as stop:
        if not progress["done"]:
            job.log_observations(writer)
        if job.preprocessor is not None and "preprocessor" not in progress["done"]:
            run.save_records("preprocessor", **job.train_preprocessor(writer))
            job.finish_phase(progress, "preprocessor", writer, stop)
        if "collect" not in progress["done"]:
            progress["data"] = job.collect()
            job.log_collect(writer, progress["data"])
            job.finish_phase(progress, "collect", writer, stop)
        run.save_records("predictor", **job.train_predictors(progress["data"], writer, progress, stop))
        actor = job.train_actor(writer, stop, progress)
        run.save_records("episodes", **actor["episodes"])
        run.save_records("junction", **actor["junction"])
        job.log_junction(writer, actor["junction"], actor["episodes"], cfg.trainer.n_episodes)
        progress["data"] = None  # the finished run keeps parameters, not the training data
        job.finish_phase(progress, "actor", writer, StopRequest())  # finished: a late signal no longer stops it
        metrics = final_metrics(actor["episodes"], job.optimal_return, cfg.trainer.final_window)
        summary = {
            "experiment": cfg.name, "task": "tmaze",
            "seeds": [cfg.seed + r for r in range(job.R)],
            "metrics": metrics,
            "optimal": {"discounted_return": job.optimal_return, "steps_to_goal": job.env.optimal_steps},
            "wall_time_s": time.perf_counter() - wall_start,
            "agent_steps_per_s": actor["agent_steps"] / max(actor["actor_time"], 1e-9),
            "diverged": job.guard.report("episode"),
        }
        log_hparams(writer, cfg, summary, cfg.trainer.n_episodes)
    return summary


def concat_records(parts: list) -> dict:
    """Junction records gathered step by step (a list of dicts of tensors) → one dict."""
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


def final_metrics(episodes: dict, optimal_return: float, window: int) -> dict:
    """CONTRACT §2 T-maze metrics over the last ``window`` (200) episodes, one value per run."""
    last = slice(-window, None)
    ret = episodes["discounted_return"][:, last].mean(1)
    correct = episodes["correct_goal"][:, last].mean(1)
    solved = (ret >= 0.95 * optimal_return) & (correct >= 0.95)
    return {"final_discounted_return": ret.tolist(), "final_steps_to_goal": episodes["steps"][:, last].mean(1).tolist(),
            "final_correct_goal_rate": correct.tolist(), "solved": solved.astype(int).tolist()}
