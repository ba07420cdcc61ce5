"""A stop request during the preprocessor's fit (issue 8/8): the RBM stops after the sweep it is in,
the run checkpoints the fit so far and exits 128 + signal, and ``resume=true`` continues the fit
and ends as the uninterrupted run — summary, records, TensorBoard. Before, a stop waited for the
fit's end (~90 min for data=mnist_full), past a cluster's grace period."""

import os
import signal

import pytest

from conftest import SHORT_ALGORITHM1, assert_same_tb_log, compose_config, train_job
from ferl.preprocessors.rbm import RBMPreprocessor
from ferl.run import checkpoint
from test_tmaze_resume import assert_same_records

PIXEL = [
    "experiment=table5_1_pixel",
    "seed=3",
    "n_runs=2",
    *SHORT_ALGORITHM1,
    "preprocessor.sweeps=6",
    "env.reservoir_size=5",
    "preprocessor.cache_dir=null",
]


@pytest.mark.parametrize("kind", ["rbm", "gaussian_rbm"])
def test_a_stop_during_the_fit_checkpoints_between_sweeps_and_resumes(tmp_path, monkeypatch, kind):
    overrides = [
        *PIXEL,
        *(
            []
            if kind == "rbm"
            else ["preprocessor=gaussian_rbm", "preprocessor.sweeps=6", "preprocessor.cache_dir=null"]
        ),
    ]
    whole = tmp_path / "whole"
    expected = train_job(compose_config(overrides), whole)

    sweep, calls = RBMPreprocessor.sweep, []

    def sweep_then_signal(self, *args):
        calls.append(1)
        if len(calls) == 3:  # SIGTERM arrives during sweep 3: the fit ends after it
            os.kill(os.getpid(), signal.SIGTERM)
        return sweep(self, *args)

    monkeypatch.setattr(RBMPreprocessor, "sweep", sweep_then_signal)
    cut = tmp_path / "cut"
    with pytest.raises(SystemExit) as stopped:
        train_job(compose_config(overrides), cut)
    assert stopped.value.code == 128 + signal.SIGTERM and len(calls) == 3
    progress = checkpoint.read(cut / "checkpoints" / "last.pt").state()["progress"]
    assert progress["done"] == [] and progress["partial"]["preprocessor"]["fit"]["sweep"] == 3
    monkeypatch.undo()

    resumed = train_job(compose_config(overrides), cut, resume=True)
    assert resumed["metrics"] == expected["metrics"]
    assert_same_records(cut, whole, ("preprocessor", "episodes", "predictor"))
    assert_same_tb_log(cut, whole)
