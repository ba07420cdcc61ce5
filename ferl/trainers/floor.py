"""Chapter 3's procedure on the digit floor (§3.5), all runs of the batch at once:

    test (before) → online SARSA(0) / Q(0) / expected-SARSA training → test (after)

as phases (``ferl.trainers.floor_tests.GreedyTests``, ``ferl.trainers.online.OnlineTD``) of a
``PhasedTrainer``; ``conf/trainer/digit_floor.yaml`` names this class and holds its arguments.
"""
from typing import Annotated

from ferl.config.params import Allowed, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.trainers.floor_tests import GreedyTests
from ferl.trainers.online import OnlineTD
from ferl.trainers.phased import PhasedTrainer


def noise_levels(levels) -> bool:
    return len(levels) > 0 and all(0 <= x <= 1 for x in levels)


class DigitFloorTrainer(PhasedTrainer):
    """``steps`` online TD steps between the test phases; run r's actor weights come from seed + r
    (no offset: the numbers of the reproduction were measured so). ``compile`` (a root key)
    compiles the chunks of steps."""

    @checked
    def __init__(self, steps: PositiveInt, log_every: PositiveInt, checkpoint_every: PositiveInt,
                 test_per_class: PositiveInt,
                 test_noise_levels: Annotated[list[float], Allowed(noise_levels, "(noise levels in [0, 1], at least one)")],
                 checkpoint_minutes: NonNegative, divergence_limit: Positive, compile_group_runs: PositiveInt,
                 prefetch: NonNegativeInt):
        self.params = dict(steps=steps, log_every=log_every, checkpoint_every=checkpoint_every,
                           test_per_class=test_per_class, checkpoint_minutes=checkpoint_minutes,
                           divergence_limit=divergence_limit)
        self.last_step = steps
        tests = dict(test_per_class=test_per_class, test_noise_levels=test_noise_levels, last_step=steps)
        super().__init__([GreedyTests("before", **tests),
                          OnlineTD(steps, log_every, checkpoint_every, checkpoint_minutes, compile_group_runs, prefetch),
                          GreedyTests("after", **tests)], divergence_limit)
