"""Chapters 4–5: predictor–actor agents on POMDPs with finite observation sets (Algorithms 1 and 2).

    [Algorithm 2] fit the preprocessor; processed observation y = ĥ(y⁽⁰⁾) (§5.2)
    collect N_sample random episodes → balance and split (§4.3.1)
    → train every predictor by BPTT in pattern mode (Eqs. 4.1–4.6; 5.1–5.2)
    → freeze them and train the actor on the state (y_t, m_t of every predictor) by SARSA(0)

as phases of a ``PhasedTrainer`` (``FitPreprocessor``, ``ferl.trainers.episodes.CollectEpisodes``,
``ferl.trainers.predictor_training.TrainPredictors``, ``ferl.trainers.actor_episodes.ActorEpisodes``).
Chapter 4 has one joint predictor; chapter 5 an observation and a reward predictor (§5.2), each
with its own memory, and (§5.3.2) an RBM preprocessor: Algorithm 2 is Algorithm 1 with the
preprocessor's phase first, which runs when the config has a preprocessor.
"""
from typing import Annotated

import numpy as np
import torch

from ferl.config.params import Allowed, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.images import IMAGE_SIDE, as_images, matrix_image, tile
from ferl.run.tensorboard import log_weights
from ferl.trainers.actor_episodes import ActorEpisodes
from ferl.trainers.episodes import CollectEpisodes
from ferl.trainers.job import SeedOffsets
from ferl.trainers.phased import Phase, PhasedTrainer
from ferl.trainers.predictor_training import TrainPredictors


class FitPreprocessor(Phase):
    """Algorithm 2's first phase (§5.3.2): the preprocessor learns from the training images, then
    processes the table of every observation, per run: what the predictors and the actor see
    from now on (``job.shared["observations"]``). Records ``preprocessor.npz``."""

    name = "preprocessor"

    def applies(self, job) -> bool:
        return job.preprocessor is not None

    def run(self, job, state) -> None:
        pre = job.preprocessor
        records = pre.fit(job.data, job.writer)
        log_weights(job.writer, "preprocessor", pre, records["reconstruction_error"].shape[1])
        raw = job.env.observation_table
        with torch.no_grad():
            job.shared["observations"] = processed = pre.transform(raw)
        job.run.save_records("preprocessor", **records, raw_observations=raw.cpu().numpy().astype(np.float16),
                             processed_observations=processed.cpu().numpy().astype(np.float16))


class Algorithm(PhasedTrainer):
    """Algorithm 1 (§4.3.1), or Algorithm 2 (§5.2) when the config has a preprocessor. Arguments:
    the collection (``n_sample``, ``collect_batch``, ``train_fraction``), the predictors'
    training (``l_training``, ``n_epoch``, ``error_every``, ``checkpoint_every_epochs``), the
    actor's (``n_episodes``, ``actor_obs_scale``, ``log_every``, ``td_sample_every``,
    ``final_window``, ``checkpoint_every``), and the job's (``checkpoint_minutes``,
    ``divergence_limit``); their meaning and values are in conf/trainer/algorithm1.yaml."""

    seed_offsets = SeedOffsets(actor=100_000)

    @checked
    def __init__(self, n_sample: PositiveInt, collect_batch: PositiveInt,
                 train_fraction: Annotated[float, Allowed(lambda x: 0 < x < 1, "in (0, 1)")],
                 l_training: PositiveInt, n_epoch: NonNegativeInt,
                 error_every: PositiveInt, n_episodes: PositiveInt, actor_obs_scale: Positive, log_every: PositiveInt,
                 td_sample_every: PositiveInt, final_window: PositiveInt, checkpoint_every_epochs: PositiveInt,
                 checkpoint_every: PositiveInt, checkpoint_minutes: NonNegative, divergence_limit: Positive):
        self.params = dict(n_sample=n_sample, train_fraction=train_fraction, l_training=l_training, n_epoch=n_epoch,
                           n_episodes=n_episodes, actor_obs_scale=actor_obs_scale, final_window=final_window)
        self.last_step = n_episodes
        super().__init__([
            FitPreprocessor(),
            CollectEpisodes(n_sample, collect_batch, train_fraction),
            TrainPredictors(l_training, n_epoch, error_every, checkpoint_every_epochs, checkpoint_minutes),
            ActorEpisodes(n_episodes, actor_obs_scale, log_every, td_sample_every, final_window, checkpoint_every,
                          checkpoint_minutes)], divergence_limit)

    def start(self, job) -> None:
        """What the agent observes: up to 8 images of every observation's reservoir (one row per
        observation of the environment's table), or the table of bit codes itself."""
        table, names = job.env.observation_table.float().cpu(), job.env.observation_names
        if table.shape[1] == IMAGE_SIDE ** 2:
            per_name = table.view(len(names), -1, table.shape[1])
            job.writer.add_image("env/observations", tile(as_images(per_name[:, :8])), 0)
        else:
            job.writer.add_image("env/observations", matrix_image(table), 0)
