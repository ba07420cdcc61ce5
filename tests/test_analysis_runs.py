"""ferl.runs on synthetic run directories: metric names as ferl.stats flattens them, and the
per-run summary as ferl.stats defines it."""

import json
import math
import statistics

import pytest

from ferl import runs
from synthetic_runs import make_floor_run


def test_metrics_are_flattened_per_level_and_summarised_by_ferl_stats(tmp_path):
    run_dir = make_floor_run(tmp_path / "sweep" / "a", n_runs=3)
    path = run_dir / "summary.json"
    summary = json.loads(path.read_text())
    summary["metrics"]["greedy_accuracy"]["0.125"] = [0.5, None, 0.75]  # a run without a value
    path.write_text(json.dumps(summary))

    metrics = runs.metrics(tmp_path / "sweep")
    assert len(metrics) == 3 and set(metrics["run"]) == {"a"}
    assert "greedy_accuracy/0.125" in metrics and "greedy_accuracy@0.125" not in metrics
    assert math.isnan(metrics["greedy_accuracy/0.125"][1])

    table = runs.summary_table(metrics).set_index("metric")
    assert "wall_time_s" not in table.index  # one number per job, not per run
    row = table.loc["greedy_accuracy/0.125"]
    assert (row["mean"], row["n_runs"]) == (0.625, 2)
    assert row["sd"] == pytest.approx(statistics.stdev([0.5, 0.75]))
    reward = summary["metrics"]["reward_per_step_last10pct"]
    row = table.loc["reward_per_step_last10pct"]
    assert row["mean"] == pytest.approx(statistics.mean(reward))
    assert row["sd"] == pytest.approx(statistics.stdev(reward))


def test_configs_are_flattened_with_dots(tmp_path):
    run_dir = make_floor_run(tmp_path / "run")
    (run_dir / ".hydra" / "config.yaml").write_text("actor:\n  n_hidden: 20\n  lr: {value: 0.1}\n")
    row = runs.configs(run_dir).iloc[0]
    assert (row["actor.n_hidden"], row["actor.lr.value"]) == (20, 0.1)
