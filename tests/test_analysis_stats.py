"""ferl.stats, the one definition of the summary statistics over runs, against the standard
library's and direct computations."""

import math
import statistics

import numpy as np
import pytest

from ferl import stats


def test_mean_sd_is_the_sample_standard_deviation():
    values = [0.3, 1.7, 2.2, 5.0, 4.1]
    mean, sd, n = stats.mean_sd(values)
    assert n == 5
    assert mean == pytest.approx(statistics.mean(values))
    assert sd == pytest.approx(statistics.stdev(values))  # ddof = 1
    assert sd != pytest.approx(statistics.pstdev(values))


def test_mean_sem_is_sd_over_root_n():
    values = [2.0, 4.0, 9.0]
    mean, sem, n = stats.mean_sem(values)
    assert (mean, n) == (5.0, 3)
    assert sem == pytest.approx(statistics.stdev(values) / math.sqrt(3))


def test_runs_without_a_value_are_left_out():
    mean, sd, n = stats.mean_sd([1.0, None, float("nan"), 3.0])
    assert (mean, n) == (2.0, 2) and sd == pytest.approx(math.sqrt(2.0))
    assert list(stats.run_values([None, 1, np.nan, 2.5])) == [1.0, 2.5]


@pytest.mark.parametrize("values", [[4.0], [None, 4.0], [np.nan, 4.0]])
def test_a_single_run_has_no_spread(values):
    mean, sd, n = stats.mean_sd(values)
    assert (mean, n) == (4.0, 1) and math.isnan(sd)
    assert math.isnan(stats.mean_sem(values)[1])


def test_no_run_has_no_mean():
    mean, sd, n = stats.mean_sd([None, float("nan")])
    assert n == 0 and math.isnan(mean) and math.isnan(sd)


def test_sem_along_the_runs_axis_matches_column_by_column():
    x = np.random.default_rng(0).normal(size=(4, 6, 2))
    expected = np.array([[statistics.stdev(x[:, t, k]) / 2.0 for k in range(2)] for t in range(6)])
    np.testing.assert_allclose(stats.sem(x), expected, rtol=1e-12)
    np.testing.assert_allclose(stats.sem(x.transpose(1, 0, 2), axis=1), expected, rtol=1e-12)
    single = stats.sem(x[:1])
    assert single.shape == (6, 2) and np.isnan(single).all()


def test_flat_metrics_names_levels_with_a_slash():
    flat = stats.flat_metrics({"reward": [1.0, 2.0], "greedy_accuracy": {"0": [0.5, 1.0], "0.125": [0.25, None]}})
    assert flat == {"reward": [1.0, 2.0], "greedy_accuracy/0": [0.5, 1.0], "greedy_accuracy/0.125": [0.25, None]}
