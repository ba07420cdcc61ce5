"""Chapters 4–5: predictor–actor agents on POMDPs with finite observation sets (Algorithms 1 and 2).

    [Algorithm 2] fit the preprocessor; processed observation y = ĥ(y⁽⁰⁾) (§5.2)
    collect N_sample random episodes → balance and split (§4.3.1)
    → train every predictor by BPTT in pattern mode (Eqs. 4.1–4.6; 5.1–5.2)
    → freeze them and train the actor on the state (y_t, m_t of every predictor) by SARSA(0)

as phases of a ``PhasedTrainer`` (``ferl.trainers.observations.FitPreprocessor``, ``ferl.trainers.episodes.CollectEpisodes``,
``ferl.trainers.predictor_training.TrainPredictors``, ``ferl.trainers.actor_episodes.ActorEpisodes``).
Chapter 4 has one joint predictor; chapter 5 an observation and a reward predictor (§5.2), each
with its own memory, and (§5.3.2) an RBM preprocessor: Algorithm 2 is Algorithm 1 with the
preprocessor's phase first, which runs when the config has a preprocessor.
"""
from typing import Annotated

from ferl import rng
from ferl.config.params import Allowed, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.interfaces import EpisodicEnvironment
from ferl.trainers.actor_episodes import ActorEpisodes
from ferl.trainers.episodes import CollectEpisodes
from ferl.trainers.observations import FitPreprocessor, log_observations
from ferl.trainers.phased import PhasedTrainer
from ferl.trainers.predictor_training import TrainPredictors


class Algorithm(PhasedTrainer):
    """Algorithm 1 (§4.3.1), or Algorithm 2 (§5.2) when the config has a preprocessor. Arguments:
    the collection (``n_sample``, ``collect_batch``, ``train_fraction``), the predictors'
    training (``l_training``, ``n_epoch``, ``error_every``, ``checkpoint_every_epochs``), the
    actor's (``n_episodes``, ``actor_obs_scale``, ``log_every``, ``td_sample_every``,
    ``final_window``, ``checkpoint_every``), and the job's (``checkpoint_minutes``,
    ``divergence_limit``); their meaning and values are in conf/trainer/algorithm1.yaml."""


    seed_offsets = rng.EPISODIC
    environment = EpisodicEnvironment

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
        log_observations(job)
