"""Algorithm 1's predictor phase (§4.3.1, Eqs. 4.1–4.8; §5.2 for Algorithm 2's several predictors).

Every predictor trains on the collected episodes (``job.outputs.episodes``) for N_epoch epochs,
each in its own shuffled order per epoch; those with one ``batch_key`` train as one
``training_batch``. ``length_order`` chooses how the lengths meet the epochs:

* ``mixed`` (the default, as §4.3.1's text: "the entire set of training data with variable
  step-lengths is shown for 400 epochs"): every epoch is one pass over every trained length,
  shuffled together;
* ``by_length`` (Algorithm 1's loop read literally: "for T = T_min to T_min + L_training − 1: train
  a predictor with D_train^T", for "the requirement of accurate prediction of a shorter sequence
  before predicting the longer sequence", §4.3.2): the epochs go to the lengths in order, the
  first N_epoch / L_training to T_min, and so on (a remainder to the first lengths); an epoch on
  D_train^T is L_training shuffled passes over it, so that every epoch takes as many SGD steps as
  a mixed one, and the whole phase the same compute.
 The prediction error of Eq. (4.7) — per step t and episode length T, mean
over the sequences, on the training and the test data — is measured every ``error_every``
epochs (Figs. 4.5, 4.10, 5.2, 5.17). Only lengths T_min … T_min + L_training − 1 are trained on.
"""

from typing import Literal

import numpy as np
import torch
from tqdm import tqdm

from ferl.config.params import ArgumentError, NonNegativeInt, PositiveInt
from ferl.predictors.popart import observe_rewards
from ferl.run.directory import CheckpointTimer
from ferl.run.tensorboard import log_weights
from ferl.trainers.episodes import episode_bytes, episode_tensors
from ferl.trainers.phased import Phase


class TrainPredictors(Phase):
    """``n_epoch`` epochs of every predictor on lengths up to T_min + ``l_training`` − 1, errors
    every ``error_every`` epochs, a checkpoint every ``checkpoint_every_epochs`` (and by the
    clock, the run node's ``checkpoint_minutes``). Records ``predictor.npz``."""

    name = "predictors"

    def applies(self, job) -> bool:
        return bool(job.predictors)

    def __init__(
        self,
        l_training: PositiveInt,
        n_epoch: NonNegativeInt,
        error_every: PositiveInt,
        checkpoint_every_epochs: PositiveInt,
        length_order: Literal["mixed", "by_length"] = "mixed",
    ):
        self.l_training, self.n_epoch, self.error_every = l_training, n_epoch, error_every
        self.checkpoint_every_epochs, self.length_order = checkpoint_every_epochs, length_order

    @classmethod
    def check_config(cls, args: dict) -> None:
        if args.get("length_order") == "by_length" and 0 < args["n_epoch"] < args["l_training"]:
            raise ArgumentError(
                "length_order",
                f"mixed, or n_epoch ≥ l_training for by_length (an epoch for each trained length; "
                f"n_epoch={args['n_epoch']}, l_training={args['l_training']})",
            )

    def epoch_orders(self, job, lengths: torch.Tensor, members: int, epoch: int) -> list[torch.Tensor]:
        """Each member's order of the training sequences in ``epoch`` (1 … N_epoch), (R, N) indices
        of the sequences whose lengths (R, N) are ``lengths`` (module docstring): a permutation of
        all N (``mixed``), or L_training permutations of the N / L_training of one length, that of
        the epoch's stage (``by_length``; balancing laid the lengths out in the same places in
        every run)."""
        R, N = lengths.shape
        if self.length_order == "mixed":
            return [torch.rand(R, N, generator=job.generator, device=job.device).argsort(1) for _ in range(members)]
        stage = (epoch - 1) * self.l_training // self.n_epoch
        where = torch.nonzero(lengths[0] == job.env.optimal_steps + stage).squeeze(1)  # (N / L_training,)
        passes = lambda: [  # noqa: E731
            where[torch.rand(R, len(where), generator=job.generator, device=job.device).argsort(1)]
            for _ in range(self.l_training)
        ]
        return [torch.cat(passes(), 1) for _ in range(members)]

    def run_bytes(self, job) -> int:
        """The peak of ``run`` (``ferl.run.footprint``'s hook): the collected episodes, each as
        float32 tensors y (T_max+1, Y + a reward), a (T_max, A) for every predictor's two splits, the
        training set and its batch, and two error arrays (T_max+1) per episode."""
        n, T = job.prepared.episodes_per_run, job.env.max_steps
        tensors = 4 * ((T + 1) * (job.n_obs + 1) + T * job.env.n_actions)
        return job.R * n * (episode_bytes(T) + (len(job.predictors) + 2) * tensors + 2 * 4 * (T + 1))

    def run(self, job, state) -> None:
        """Every group of predictors not yet trained; a finished group is checkpointed."""
        state = state or {"records": {}, "done": [], "group": None}
        groups: dict[tuple, list[str]] = {}  # batch_key → the names of the predictors that train as one batch
        for name, p in job.predictors.items():
            groups.setdefault(p.batch_key, []).append(name)
        for names in groups.values():
            if names[0] not in state["done"]:
                state["records"] |= self.train_group(job, names, state)
                state["done"] += names
                state["group"] = None
                job.checkpoint(self.name, state)
        job.run.save_records("predictor", job.R, **state["records"])

    def lengths(self, job) -> range:
        """The episode lengths T_min … T_max that the data hold."""
        return range(job.env.optimal_steps, job.env.max_steps + 1)

    def prediction_errors(self, job, tensors: tuple, predictor) -> np.ndarray:
        """(R, nT, Tmax+1) Eq. (4.7): mean over the sequences of each length of Eq. (4.8) per step;
        ``tensors`` (y, a, r, lengths) of a data split."""
        lengths = tensors[3]
        err = predictor.prediction_errors(*tensors)  # (R, B, Tmax+1), NaN on padding
        out = [
            torch.nanmean(torch.where((lengths == T).unsqueeze(-1), err, torch.nan), dim=1) for T in self.lengths(job)
        ]
        return torch.stack(out, 1).cpu().numpy().astype(np.float32)

    def train_group(self, job, names: list, state: dict) -> dict:
        """The named predictors for N_epoch epochs, from the epoch a checkpoint left them at."""
        data, R = job.outputs.episodes, job.R
        train = data.train
        members = [job.predictors[name] for name in names]
        # the training set proper: lengths T_min … T_min + L_training − 1; balancing laid the
        # lengths out in the same blocks in every run, so run 0's positions hold for all
        trainable = train.lengths[0] <= job.env.optimal_steps + self.l_training - 1
        fit = train.select(torch.nonzero(trainable).squeeze(1).expand(R, -1))
        y, a, _, lengths = episode_tensors(job, fit, None)
        partial = state["group"] or {}
        if partial.get("names") != names:  # a fresh start: the fit's rewards set a normalised reward head's statistics
            observe_rewards(members, fit.rewards, fit.lengths)
        batch = type(members[0]).training_batch(
            members, y, a, [p.reward_targets(job.env.reward_values, fit.rewards) for p in members], lengths
        )
        if job.fast:  # a batch without a fast path stays eager (``TrainingBatchBase.fuse``); every
            # step unrolled to the longest trained length: one graph whatever lengths an epoch holds
            batch.fuse(job.device, unroll_to=int(lengths.max()))
        splits = {
            (name, s): episode_tensors(job, split, p)
            for name, p in zip(names, members)
            for s, split in (("train", data.train), ("test", data.test))
        }
        if partial.get("names") == names:
            errors, epochs, start = partial["errors"], partial["epochs"], partial["epoch"]
        else:
            errors = {
                name: {s: [self.prediction_errors(job, splits[name, s], p)] for s in ("train", "test")}
                for name, p in zip(names, members)
            }
            epochs, start = [0], 0
            for name, p in zip(names, members):
                log_weights(job.writer, f"predictor_{name}", p, 0)
        clock = CheckpointTimer(job.control.checkpoint_minutes)
        for epoch in (
            bar := tqdm(
                range(start + 1, self.n_epoch + 1),
                desc=f"predictor {'+'.join(names)}",
                unit="epoch",
                initial=start,
                total=self.n_epoch,
                mininterval=1.0,
            )
        ):
            batch.train_epoch(self.epoch_orders(job, lengths, len(members), epoch))
            if epoch % self.error_every == 0 or epoch == self.n_epoch:
                epochs.append(epoch)
                for name, p in zip(names, members):
                    self.log_errors(job, name, p, errors[name], splits, epoch)
                bar.set_postfix(
                    error_test=" ".join(f"{np.nanmean(errors[n]['test'][-1]):.4f}" for n in names), refresh=False
                )
            if (
                epoch % self.checkpoint_every_epochs == 0 or job.stop.requested or clock.due()
            ) and epoch < self.n_epoch:
                state["group"] = {"names": names, "epoch": epoch, "errors": errors, "epochs": epochs}
                job.checkpoint(self.name, state)
        lengths_all = np.arange(job.env.optimal_steps, job.env.max_steps + 1)
        records: dict[str, np.ndarray] = {}
        for name, p in zip(names, members):
            log_weights(job.writer, f"predictor_{name}", p, self.n_epoch)
            records |= {
                f"{name}_lengths": lengths_all,
                f"{name}_epochs": np.asarray(epochs),
                **{f"{name}_error_{s}": np.stack(errors[name][s], 1) for s in ("train", "test")},
            }
        return records

    def log_errors(self, job, name: str, predictor, errors: dict, splits: dict, epoch: int) -> None:
        """Append the Eq. 4.7 errors of both splits to ``errors`` and log them (mean, and test per T)."""
        for split in ("train", "test"):
            errors[split].append(self.prediction_errors(job, splits[name, split], predictor))
            job.writer.add_scalar(f"predictor_{name}/error_{split}", float(np.nanmean(errors[split][-1])), epoch)
        for T, value in zip(self.lengths(job), np.nanmean(errors["test"][-1], axis=(0, 2))):
            job.writer.add_scalar(f"predictor_{name}/error_test_T{T}", float(value), epoch)
