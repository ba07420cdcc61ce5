"""A new environment and a new predictor through configuration alone (issue 1/8): the toy
components of tests/toy_components.py, selected by the ``_target_`` of their own YAML files in
tests/toy/conf (put on Hydra's search path), train end to end through train.py under Algorithm 1
with the FERL actor, and analyze.py gives the run its generic figures. Nothing in ferl/ names them."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import ROOT, run_train
from ferl.interfaces import EpisodicEnvironment, Predictor
from toy_components import CueEnv, TracePredictor

TESTS = Path(__file__).resolve().parent
TOY = [f"hydra.searchpath=[file://{TESTS / 'toy' / 'conf'}]", "experiment=toy_cue"]
NAMES = ("toy_components", "CueEnv", "TracePredictor", "toy_cue", "toy_trace", "toy_phases", "ActorWeightNorm")


@pytest.fixture(scope="module")
def toy_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("toy") / "run"
    # compile=true, a user's default: components without the fast path's optional hooks
    # (TrainingBatch.fuse, an environment's traceable_steps) run with no warning: the predictor's
    # training eagerly, the environment's steps eagerly between calls of the agent's compiled step
    result = run_train(*TOY, "compile=true", f"hydra.run.dir={run_dir}", env={**os.environ, "PYTHONPATH": str(TESTS)})
    assert result.returncode == 0, result.stderr[-3000:]
    assert "compile=true" not in result.stderr
    compiled = [line for line in result.stderr.splitlines() if line.startswith("ferl: compiled")]
    assert all(line.startswith("ferl: compiled the agent's half of a step in ") for line in compiled), compiled
    return run_dir


def test_the_toys_meet_the_interfaces():
    env = CueEnv(3, torch.Generator().manual_seed(0))
    assert isinstance(env, EpisodicEnvironment)
    assert isinstance(TracePredictor(3, env.observation_size, env.n_actions), Predictor)


def test_cue_env_rewards_the_cued_choice():
    env = CueEnv(4, torch.Generator().manual_seed(0), delay=2)
    cue = env.cue.clone()
    for _ in range(2):  # the delay: any action, no reward, no end
        _, reward, terminated, _ = env.step(torch.zeros(4, dtype=torch.long))
        assert (reward == 0).all() and not terminated.any()
    assert env.probe.all()
    _, reward, terminated, _ = env.step(cue)
    assert (reward == 1).all() and terminated.all() and env.outcomes()["correct"].all()


def test_trains_end_to_end_and_learns(toy_run):
    summary = json.loads((toy_run / "summary.json").read_text())
    manifest = json.loads((toy_run / "records" / "run.json").read_text())
    assert summary["task"] == manifest["task"] == "cue"
    assert manifest["env"]["class"] == "toy_components.CueEnv"
    assert manifest["predictors"]["trace"]["class"] == "toy_components.TracePredictor"
    assert manifest["trainer"]["phases"] == ["collect", "predictors", "actor"]
    metrics = summary["metrics"]
    assert set(metrics) == {
        "final_discounted_return",
        "final_steps_to_goal",
        "final_correct_rate",
        "solved",
        "env_steps_total",
        "env_steps_to_solve",
        "episodes_to_solve",
    }
    assert summary["optimal"]["discounted_return"] == pytest.approx(0.95**2)
    # the cue is only in the trace at the choice: an actor without memory is right half the time
    assert min(metrics["final_correct_rate"]) > 0.9, metrics
    junction = np.load(toy_run / "records" / "probe.npz")  # activations at the choice, labelled by the cue
    assert set(np.unique(junction["cue"])) == {0, 1} and junction["memory_trace"].shape[1] == 4
    predictor = np.load(toy_run / "records" / "predictor.npz")
    errors = predictor["trace_error_train"]  # (R, epochs, T, t): learning lowers the prediction error
    assert np.nanmean(errors[:, -1]) < np.nanmean(errors[:, 0])


def test_analyze_writes_the_generic_figures(toy_run):
    result = subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(toy_run)], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]
    figures = {p.stem for p in (toy_run / "analysis").glob("*.png")}
    assert {"learning_curves", "td_errors"} <= figures and any("prediction" in f for f in figures), figures
    report = (toy_run / "analysis" / "report.md").read_text()
    assert "## Claims" not in report and "dissertation" not in report  # a task of its own: no one's claims


def test_nothing_in_ferl_names_the_toys():
    for path in (ROOT / "ferl").rglob("*"):
        if path.is_file() and path.suffix in (".py", ".yaml", ".md"):
            text = path.read_text()
            assert not any(name in text for name in NAMES), path
    for path in (ROOT / "conf").rglob("*.yaml"):
        assert not any(name in path.read_text() for name in NAMES), path


def test_a_phase_from_tests_is_inserted_by_yaml_alone(tmp_path):
    """tests/toy/conf/trainer/toy_weight_norm.yaml adds tests/toy_phases.py's ActorWeightNorm to
    Algorithm 1's phases; train.py runs it after the actor phase, and its metric is the 1-norm of
    the trained actor's state weights, as the final checkpoint holds them (computed here in NumPy)."""
    from ferl.run import checkpoint

    run_dir = tmp_path / "run"
    result = run_train(
        *TOY,
        "trainer=toy_weight_norm",
        "trainer.n_epoch=2",
        "trainer.n_episodes=60",
        "trainer.log_every=20",
        "trainer.td_sample_every=20",
        "trainer.final_window=20",
        "compile=false",
        f"hydra.run.dir={run_dir}",
        env={**os.environ, "PYTHONPATH": str(TESTS)},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    manifest = json.loads((run_dir / "records" / "run.json").read_text())
    assert manifest["trainer"]["phases"] == ["collect", "predictors", "actor", "weight_norm"]
    norms = json.loads((run_dir / "summary.json").read_text())["metrics"]["actor_weight_norm"]
    W = checkpoint.read(run_dir / "checkpoints" / "last.pt").state()["actor"]["W_sh"].numpy().astype(np.float64)
    assert norms == pytest.approx(np.abs(W).reshape(len(W), -1).sum(1), rel=1e-5)
    assert len(norms) == 2 and norms[0] != norms[1]  # the trained weights of each run
