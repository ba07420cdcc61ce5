"""The meta-parameter schedules (ferl/schedules.py) against their formulas written out: the
linear and geometric ramps over the whole training or its first share ``over``, held after it."""

import numpy as np
import pytest

from ferl.schedules import Exponential, Linear


@pytest.mark.parametrize("over", [1.0, 0.7, 0.25])
def test_linear_rises_over_its_share_of_the_training_then_holds(over):
    start, end = 2.0, 30.0
    for p in np.linspace(0, 1, 41):
        want = start + (end - start) * p / over if p < over else end
        assert Linear(start, end, over)(float(p)) == pytest.approx(want, rel=1e-12)
    assert Linear(start, end)(0.4) == start + (end - start) * 0.4  # over = 1: the dissertation's ramp, exactly


@pytest.mark.parametrize("over", [0.0, -0.5, 1.5])
def test_a_share_outside_0_1_is_refused(over):
    for schedule in (Linear, Exponential):
        with pytest.raises(ValueError, match=r"over is a share of the training in \(0, 1\]"):
            schedule(0.1, 1.0, over)


@pytest.mark.parametrize("over", [1.0, 0.5])
def test_exponential_interpolates_geometrically_then_holds(over):
    for p in (0.0, 0.3, 0.5, 0.8, 1.0):
        assert Exponential(0.1, 0.01, over)(p) == pytest.approx(0.1 * 0.1 ** min(1.0, p / over), rel=1e-12)
