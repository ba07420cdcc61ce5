"""Algorithm 1's collection phase (§4.3.1 "Training procedure"): the predictors' data.

N_sample random-policy episodes per run (``ferl.trainers.episodes.collect_random_episodes``),
balanced to an equal number of episodes per step-length T = T_min … T_max and split into training
and test data (``balance_and_split``), handed on as ``job.outputs.episodes``
(``ferl.trainers.handoffs.SplitEpisodes``).
"""

from typing import Annotated

from ferl.config.params import Allowed, ConfigError, PositiveInt
from ferl.trainers.episodes import balance_and_split, collect_random_episodes, episode_bytes
from ferl.trainers.handoffs import SplitEpisodes
from ferl.trainers.phased import Phase


class CollectEpisodes(Phase):
    """Algorithm 1's data (§4.3.1): ``n_sample`` random-policy episodes per run, balanced over the
    lengths T_min … T_max and split ``train_fraction`` / rest into training and test data (handed
    to the next phases as ``job.outputs.episodes``, with the steps they took, ``random_steps``). ``collect_batch`` episodes are stepped at
    once (speed only: the draws do not depend on it)."""

    name = "collect"

    def __init__(
        self,
        n_sample: PositiveInt,
        collect_batch: PositiveInt,
        train_fraction: Annotated[float, Allowed(lambda x: 0 < x < 1, "in (0, 1)")],
    ):
        self.n_sample, self.collect_batch, self.train_fraction = n_sample, collect_batch, train_fraction

    def applies(self, job) -> bool:
        """The random episodes are the predictors' data: a memoryless agent (``predictor=none``) acts at once."""
        return bool(job.predictors)

    def prepare(self, job) -> None:
        job.prepared.episodes_per_run = self.n_sample  # the size of the next phases' data
        if job.env.discovers_observations:
            raise ConfigError(
                f"trainer: Algorithm 1's predictors learn from episodes collected beforehand, on ids of a fixed "
                f"observation table, and {job.env.task} environments discover their observations as they "
                f"run: use trainer=online, or predictor=none"
            )

    def copies(self, job) -> int:
        """Environment copies per run stepped at once (``collect_batch`` episodes in all)."""
        return max(1, min(self.n_sample, self.collect_batch // job.R))

    def run_bytes(self, job) -> int:
        """The peak of ``run`` beyond what the job holds (``ferl.run.footprint``'s hook): the
        collected rounds, their stack and the episodes kept, each (obs, actions int64, rewards
        float32, length int64) padded to T_max."""
        copies = self.copies(job)
        collected = job.R * copies * -(-self.n_sample // copies)
        return (2 * collected + job.R * self.n_sample) * episode_bytes(job.env.max_steps)

    def run(self, job, state) -> None:
        env = job.make_env(job.R * self.copies(job))
        episodes = collect_random_episodes(env, self.n_sample, job.R, job.generator)
        job.outputs.random_steps = episodes.lengths.sum(1).cpu().numpy()  # env steps the data cost each run
        train, test, (n_train, n_test) = balance_and_split(
            episodes, job.env.optimal_steps, job.env.max_steps, self.train_fraction, job.generator
        )
        job.outputs.episodes = SplitEpisodes(train, test, n_train, n_test)
        job.writer.add_scalar("collect/train_sequences", train.lengths.shape[1], 0)
        job.writer.add_scalar("collect/test_sequences", test.lengths.shape[1], 0)
        job.writer.add_scalar("collect/train_per_length", n_train, 0)
