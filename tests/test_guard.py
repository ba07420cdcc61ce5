"""The per-run divergence guard (ferl/run/guard.py): which run, at which step, why."""

import math

import torch

from ferl.run.guard import DivergenceGuard


def test_first_bad_step_of_each_run_and_only_those_runs_frozen():
    guard = DivergenceGuard(4, limit=100.0, seeds=[7, 8, 9, 10], device="cpu")
    errors = torch.randn(50, 4)
    errors[13, 1] = math.nan
    errors[20, 1] = math.inf  # later trouble of the same run does not move its step
    errors[31, 3] = -250.0  # finite but beyond the limit
    guard.check(errors, first_step=1000)
    assert guard.alive.squeeze(1).tolist() == [True, False, True, False]
    assert guard.report() == [
        {"run": 1, "seed": 8, "step": 1013, "reason": "non-finite TD error"},
        {"run": 3, "seed": 10, "step": 1031, "reason": "|TD error| 250 > limit 100"},
    ]

    delta = torch.full((4, 1), math.nan)
    masked = guard.mask(delta)
    assert masked[[1, 3]].eq(0).all() and masked[[0, 2]].isnan().all()

    later = torch.randn(10, 4)  # a frozen run is reported once, at its first step
    later[:, [1, 3]] = math.nan
    guard.check(later, first_step=1050)
    assert [d["step"] for d in guard.report()] == [1013, 1031]


def test_healthy_runs_pass_unchanged_and_state_round_trips():
    guard = DivergenceGuard(3, limit=1e6, seeds=[0, 1, 2], device="cpu")
    errors = torch.randn(20, 3) * 50
    guard.check(errors, first_step=0)
    assert guard.report() == [] and guard.alive.all()
    delta = torch.randn(3, 1)
    assert torch.equal(guard.mask(delta), delta)

    errors[4, 0] = math.nan
    guard.check(errors, first_step=0)
    copy = DivergenceGuard(3, limit=1e6, seeds=[0, 1, 2], device="cpu")
    copy.load_state_dict(guard.state_dict())
    assert copy.report() == guard.report() and torch.equal(copy.alive, guard.alive)


# ---- a NaN injected into one run of a real batch ----------------------------------------------

import pytest  # noqa: E402

from conftest import train_job  # noqa: E402

FLOOR = [
    "experiment=ch3_floor",
    "n_runs=3",
    "trainer.steps=600",
    "trainer.test_per_class=5",
    "trainer.log_every=100",
    "trainer.test_noise_levels=[0.125]",
]
MAZE = [
    "experiment=table4_1_matching",
    "n_runs=3",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=200",
    "trainer.log_every=50",
    "trainer.final_window=50",
]
RESERVOIR = [
    "experiment=table5_1_pixel",
    "n_runs=3",
    "env.reservoir_size=5",
    "preprocessor.sweeps=20",
    "trainer.n_sample=300",
    "trainer.n_epoch=2",
    "trainer.n_episodes=200",
    "trainer.log_every=50",
    "trainer.final_window=50",
]


def poison_run_1_at(update, at: int):
    """Wrap FERLActor.update: from its `at`-th call on, run 1's weights are NaN."""
    calls = [0]

    def wrapped(self, *args):
        calls[0] += 1
        if calls[0] == at:
            self.W_sh[1] = math.nan
        return update(self, *args)

    return wrapped


@pytest.mark.parametrize(
    "task, overrides, unit, at",
    [
        ("digit_floor", FLOOR, "step", 250),
        ("tmaze", MAZE, "episode", None),
        ("tmaze", RESERVOIR, "episode", None),  # images drawn from a reservoir every step
    ],
)
def test_injected_nan_marks_only_that_run(compose_cfg, tmp_path, monkeypatch, task, overrides, unit, at):
    from ferl.actors.free_energy import FERLActor

    cache = ["preprocessor.cache_dir=" + str(tmp_path / "cache")] if "experiment=table5_1_pixel" in overrides else []
    clean = train_job(compose_cfg(overrides + cache), tmp_path / "clean")
    assert clean["diverged"] == []

    at = at or 400  # T-maze: a few steps into episode ~100
    monkeypatch.setattr(FERLActor, "update", poison_run_1_at(FERLActor.update, at))
    poisoned = train_job(compose_cfg(overrides + cache), tmp_path / "poisoned")
    [report] = poisoned["diverged"]
    assert (report["run"], report["seed"], report["reason"]) == (1, 1, "non-finite TD error")
    if task == "digit_floor":
        # the step loop's call k updates after step k − 1; the first non-finite δ is that of step k
        assert report[unit] == at
    else:
        assert 0 < report[unit] < 200
    # the other runs draw the same random numbers and never interact with run 1: on the T-maze
    # too, where run 1's broken policy makes the lockstep episodes longer than they were
    for name, values in clean["metrics"].items():
        if isinstance(values, dict):
            for level in values:
                assert [values[level][r] for r in (0, 2)] == [poisoned["metrics"][name][level][r] for r in (0, 2)]
        else:
            assert [values[r] for r in (0, 2)] == [poisoned["metrics"][name][r] for r in (0, 2)]
    assert clean["metrics"] != poisoned["metrics"]
