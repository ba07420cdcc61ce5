"""Chapter 3's procedure on the digit floor (§3.5), all runs of the batch at once:

    test (before) → online SARSA(0) / Q(0) / expected-SARSA training → test (after)

as phases (``ferl.trainers.floor_tests.GreedyTests``, ``ferl.trainers.online.OnlineTD``) of a
``PhasedTrainer``; ``conf/trainer/digit_floor.yaml`` names this class and holds its arguments.
"""
from typing import Annotated

from ferl.config.params import Allowed, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.trainers.continuing import OnlineTDTrainer
from ferl.trainers.floor_tests import GreedyTests


def noise_levels(levels) -> bool:
    return len(levels) > 0 and all(0 <= x <= 1 for x in levels)


class DigitFloorTrainer(OnlineTDTrainer):
    """``steps`` online TD steps between the test phases; run r's actor weights come from seed + r
    (no offset: the numbers of the reproduction were measured so). ``compile`` (a root key)
    compiles the chunks of steps."""

    @checked
    def __init__(self, steps: PositiveInt, log_every: PositiveInt, checkpoint_every: PositiveInt,
                 test_per_class: PositiveInt,
                 test_noise_levels: Annotated[list[float], Allowed(noise_levels, "(noise levels in [0, 1], at least one)")],
                 checkpoint_minutes: NonNegative, divergence_limit: Positive, compile_group_runs: PositiveInt,
                 prefetch: NonNegativeInt):
        self.tests = dict(test_per_class=test_per_class, test_noise_levels=test_noise_levels, last_step=steps)
        super().__init__(steps, log_every, checkpoint_every, checkpoint_minutes, divergence_limit, compile_group_runs,
                         prefetch)
        self.params["test_per_class"] = test_per_class

    def around(self, online) -> list:
        return [GreedyTests("before", **self.tests), online, GreedyTests("after", **self.tests)]
