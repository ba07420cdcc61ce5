"""An outside environment that fails (ferl/envs/boundary.py): the failing run is frozen like a
diverged one and named (env id, run, episode, step) on one stderr line, the other runs finish
with the numbers they have without the fault, summary.json is strict JSON, and a resumed run
goes on without stepping the failed environment again.

The environment is tests/outside_env.py's ``Faulty``: CueRecall with a MultiDiscrete([3, 2])
observation whose run 1 (keyed by its seed) misbehaves from its 100th step on. Episodes last 3
steps in lockstep, so step 100 is episode 33's first step.
"""

import json
import os
import re
import shutil
import sys

import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import ROOT, compose_config, run_train, train_job
from ferl.envs.boundary import within
from ferl.envs.gymnasium_vector import EnvironmentFault, GymnasiumEnv
from ferl.run import checkpoint
from ferl.run.directory import RunDir
from ferl.trainers.job import SeedOffsets

TESTS = ROOT / "tests"
ENV = {**os.environ, "PYTHONPATH": str(TESTS)}
sys.path.insert(0, str(TESTS))
FAULTY = "outside_env:Faulty-v0"
BAD_RUN, AT, EPISODE, STEP = 1, 100, 33, 1
BASE = [
    "experiment=popgym_repeat_previous_easy",
    f"env.id={FAULTY}",
    "env.optimal_return=0.8",
    "env.reward_scale=5",
    "trainer.n_episodes=60",
    "trainer.replay_sample=16",
    "trainer.log_every=20",
    "trainer.checkpoint_every=20",
    "n_runs=3",
    f"+env.kwargs.at={AT}",
]
WHAT = {
    "raise": "raised",
    "shape": "returned an observation outside its space MultiDiscrete([3 2])",
    "range": "returned an observation outside its space MultiDiscrete([3 2])",
    "nan_reward": "returned the reward nan",
    "inf_reward": "returned the reward inf",
}
DETAIL = {
    "raise": ": ValueError: operands could not be broadcast together with shapes (3,) (2,) (at step 100)",
    "shape": ": array([0, 0, 0])",
    "range": ": array([3, 1])",
    "nan_reward": "",
    "inf_reward": "",
}


def overrides(fault: str, bad_run: int | None = BAD_RUN) -> list:
    """The tiny run, with run ``bad_run``'s environment (None: none) failing as ``fault`` says."""
    bad_seed = -1 if bad_run is None else SeedOffsets().env + bad_run  # the env's seed: seed + offset + run
    return [*BASE, f"+env.kwargs.fault={fault}", f"+env.kwargs.bad_seed={bad_seed}"]


def strict(text: str) -> dict:
    """JSON as any parser reads it: NaN and Infinity are not JSON."""

    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def train(run_dir, fault: str, bad_run: int | None = BAD_RUN, resume: bool = False) -> dict:
    """What train.py does, in process: train, then write summary.json; returns it as read back."""
    summary = train_job(compose_config(overrides(fault, bad_run)), run_dir, resume)
    RunDir(run_dir).write_summary(summary)
    return strict((run_dir / "summary.json").read_text())


def fault_lines(stderr: str) -> list[str]:
    """The lines of stderr (tqdm's bars end in carriage returns) that report a frozen run."""
    return [line for line in re.split(r"[\r\n]+", stderr) if line.startswith("ferl: run")]


def expected_line(fault: str) -> str:
    return (
        f"ferl: run {BAD_RUN} (seed {BAD_RUN}): env {FAULTY!r} {WHAT[fault]} at episode {EPISODE}, step {STEP}"
        f"{DETAIL[fault]}; frozen, the other runs go on"
    )


@pytest.fixture(scope="module")
def healthy(tmp_path_factory):
    """The same runs with no environment failing."""
    run_dir = tmp_path_factory.mktemp("healthy") / "run"
    return train(run_dir, "raise", bad_run=None), np.load(run_dir / "records" / "episodes.npz")


@pytest.mark.parametrize("fault", list(WHAT))
def test_a_failing_environment_freezes_its_run_only(tmp_path, capsys, healthy, fault):
    want, want_episodes = healthy
    capsys.readouterr()
    summary = train(tmp_path / "run", fault)
    err = capsys.readouterr().err
    assert fault_lines(err) == [expected_line(fault)], err
    assert summary["diverged"] == [
        {
            "run": BAD_RUN,
            "seed": BAD_RUN,
            "episode": EPISODE,
            "env_id": FAULTY,
            "step": STEP,
            "reason": expected_line(fault)[len("ferl: run 1 (seed 1): ") : -len("; frozen, the other runs go on")],
        }
    ]
    for name, values in summary["metrics"].items():  # the other runs: exactly their numbers without the fault
        assert values[BAD_RUN] is None, name  # the failed run's episodes after the fault are stand-ins
        assert [v for r, v in enumerate(values) if r != BAD_RUN] == [
            v for r, v in enumerate(want["metrics"][name]) if r != BAD_RUN
        ], name
    episodes = np.load(tmp_path / "run" / "records" / "episodes.npz")
    healthy_runs = [r for r in range(3) if r != BAD_RUN]
    for key in ("return", "steps", "td_abs_mean"):
        np.testing.assert_array_equal(episodes[key][healthy_runs], want_episodes[key][healthy_runs])
        assert np.isfinite(episodes[key]).all(), key  # a NaN or infinite reward never reached a record
    np.testing.assert_array_equal(episodes["return"][BAD_RUN, :EPISODE], want_episodes["return"][BAD_RUN, :EPISODE])


def test_exit_code_zero_one_line_and_strict_summary_through_train_py(tmp_path):
    """train.py: the healthy runs finished, so exit 0 with the failed run listed in ``diverged``
    (as a diverged run is), summary.json strict although the failed run's return was infinite."""
    run_dir = tmp_path / "run"
    result = run_train(*overrides("inf_reward"), f"hydra.run.dir={run_dir}", env=ENV)
    assert result.returncode == 0, result.stderr[-2000:]
    assert fault_lines(result.stderr) == [expected_line("inf_reward")]
    summary = strict((run_dir / "summary.json").read_text())
    assert [d["run"] for d in summary["diverged"]] == [BAD_RUN]
    assert summary["metrics"]["final_return"][BAD_RUN] is None
    for path in (run_dir / "records").glob("*.json"):
        strict(path.read_text())


def test_resume_after_the_fault_goes_on_without_stepping_the_failed_environment(tmp_path, capsys):
    """From the checkpoint at episode 40 (after run 1's environment raised at episode 33, and
    raising at every step since): resume=true finishes the healthy runs as the uninterrupted run
    did, reports nothing new and keeps run 1 frozen."""
    whole = train(tmp_path / "whole", "raise")
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "whole", cut)
    (cut / "summary.json").unlink()
    shutil.move(cut / "checkpoints" / checkpoint.PREVIOUS, cut / "checkpoints" / checkpoint.LAST)
    saved = checkpoint.read(cut / "checkpoints" / checkpoint.LAST).state()
    assert saved["progress"]["partial"]["online"]["episode"] == 40 and saved["env"]["failed"] == [False, True, False]
    assert saved["env"]["envs"][BAD_RUN] == b""  # the failed environment is not kept: never stepped again
    capsys.readouterr()
    resumed = train(cut, "raise", resume=True)
    assert fault_lines(capsys.readouterr().err) == []
    assert resumed["metrics"] == whole["metrics"] and resumed["diverged"] == whole["diverged"]
    assert [d["run"] for d in resumed["diverged"]] == [BAD_RUN]


def test_an_observation_outside_its_space_is_not_encoded():
    """[3, 1] in MultiDiscrete([3, 2]) is named, not turned into bits; used directly (no training
    job to freeze the run), the environment raises."""
    env = GymnasiumEnv(3, None, 10, FAULTY, kwargs={"fault": "range", "at": 4, "bad_seed": 11})
    env.reset()
    with pytest.raises(EnvironmentFault) as caught:
        for _ in range(2 * env.max_steps):
            env.step(torch.zeros(3, dtype=torch.long))
            if bool(env.done.all()):
                env.reset()
    assert str(caught.value) == (
        f"run 1 (seed 11): env {FAULTY!r} returned an observation outside its space "
        f"MultiDiscrete([3 2]) at episode 1, step 1: array([3, 1])"
    )
    table = env.observation_table[: len(env.ids)]
    assert (table[:, :3].sum(1) == 1).all() and (table[:, 3:].sum(1) == 1).all()  # every row one symbol, one flag


@pytest.mark.parametrize(
    "space, value, inside",
    [
        (spaces.MultiDiscrete([3, 2]), np.array([2, 1]), True),
        (spaces.MultiDiscrete([3, 2]), np.array([3, 1]), False),
        (spaces.MultiDiscrete([3, 2]), np.array([0, 0, 0]), False),
        (spaces.Discrete(4), np.int64(4), False),
        (spaces.Box(0, 1, (2,), np.float32), np.array([0.5, 1.0]), True),  # float64 in a float32 box: the same bits
        (spaces.Box(0, 1, (2,), np.float32), np.array([0.5, np.nan]), False),
        (spaces.Box(0, 1, (2,), np.float32), np.array([0.5]), False),
        (spaces.Tuple((spaces.Discrete(3), spaces.Discrete(2))), (2, 1), True),
        (spaces.Tuple((spaces.Discrete(3), spaces.Discrete(2))), (2,), False),
        (spaces.Dict({"a": spaces.Discrete(2)}), {"b": 0}, False),
    ],
)
def test_within_its_space(space, value, inside):
    assert within(space, value) is inside
