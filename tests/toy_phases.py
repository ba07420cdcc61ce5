"""A phase written outside ferl/ (tests/test_extension.py inserts it into Algorithm 1 by YAML alone:
tests/toy/conf/trainer/toy_weight_norm.yaml)."""

from typing import Literal

from ferl.trainers.phased import Phase


class ActorWeightNorm(Phase):
    """The ``ord``-norm of every run's actor state weights W_sh (R, S, H), flattened per run: the
    summary.json metric ``actor_weight_norm`` (one value per run)."""

    def __init__(self, ord: Literal[1, 2] = 2):
        self.ord = ord

    def metric_names(self, job) -> list[str]:
        return ["actor_weight_norm"]

    def run(self, job, state) -> None:
        weights = job.actor.state_weights().flatten(1)  # (R, S·H)
        job.metrics["actor_weight_norm"] = weights.norm(p=self.ord, dim=1).tolist()
