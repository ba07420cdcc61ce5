"""The online trainer (§5.4) and sample efficiency: learning at reduced scale, the steps counted
against the recorded episodes, ``env_steps_to_solve`` against a loop over every window, β's rule,
the curiosity bonus against the predictor's own sequence outputs, and SIGTERM → resume."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import compose_config, eager, train_job
from ferl.stats import SOLVED_SHARE, sample_efficiency
from test_tmaze_resume import progress, records
from test_train_cli import summary

ROOT = Path(__file__).resolve().parents[1]
ONLINE = [
    "experiment=table4_1_regular",
    "trainer=online",
    "n_runs=2",
    "trainer.n_episodes=1500",
    "trainer.log_every=100",
    "trainer.checkpoint_every=100",
]


@pytest.fixture(scope="module")
def online_run(tmp_path_factory) -> tuple[Path, dict]:
    run_dir = tmp_path_factory.mktemp("online") / "run"
    return run_dir, train_job(compose_config(ONLINE), run_dir)


def test_online_agent_learns_the_regular_maze(online_run):
    """Regular T-maze, corridor 3, 2 runs × 1 500 episodes, learning from the first episode: the
    last 200 episodes end at the rewarded goal far above chance (0.5 of the goal entries)."""
    _, result = online_run
    assert min(result["metrics"]["final_correct_goal_rate"]) > 0.8, result["metrics"]


def test_env_steps_are_the_recorded_episodes_steps(online_run):
    run_dir, result = online_run
    episodes = records(run_dir, "episodes")
    assert result["metrics"]["env_steps_total"] == episodes["steps"].sum(1).tolist()
    online = records(run_dir, "online")
    # β is 0 until the first episode's error is known, then follows the rule, never above the schedule
    assert (online["beta"][:, 0] == 0).all() and (online["beta"] <= 10.0 * np.arange(1500) / 1500 + 1e-5).all()
    assert online["prediction_error"][:, -200:].mean() < 0.5 * online["prediction_error"][:, 0].mean()


def test_env_steps_to_solve_against_a_loop_over_windows():
    """The first window of W episodes meeting the solved criterion, found by a plain loop."""
    rng = np.random.default_rng(0)
    R, N, W, opt = 4, 60, 10, 4.0
    good = np.arange(N) > rng.integers(15, 70, size=(R, 1))  # runs improve at random points (one never)
    ep = {
        "discounted_return": np.where(good, 4.2, -1.0) + rng.normal(0, 0.3, (R, N)),
        "steps": rng.integers(3, 11, size=(R, N)),
        "correct_goal": good | (rng.random((R, N)) < 0.3),
    }
    random_steps = rng.integers(0, 1000, size=R)
    got = sample_efficiency(ep, random_steps, ("discounted_return", opt), W, ["correct_goal"])
    for r in range(R):
        want = None
        for k in range(W - 1, N):
            window = slice(k - W + 1, k + 1)
            if (
                ep["discounted_return"][r, window].mean() >= SOLVED_SHARE * opt
                and ep["correct_goal"][r, window].mean() >= SOLVED_SHARE
            ):
                want = k
                break
        steps = int(random_steps[r] + ep["steps"][r, : want + 1].sum()) if want is not None else None
        assert got["env_steps_to_solve"][r] == steps
        assert got["episodes_to_solve"][r] == (want + 1 if want is not None else None)
        assert got["env_steps_total"][r] == random_steps[r] + ep["steps"][r].sum()
    assert None in got["env_steps_to_solve"] and any(v is not None for v in got["env_steps_to_solve"])


def online_phase(*overrides):
    """The online phase of a composed config, set up on its job (nothing trained)."""
    from hydra.utils import instantiate
    from omegaconf import open_dict

    cfg = compose_config([*ONLINE, *overrides])
    with open_dict(cfg):
        del cfg["hydra"]
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, torch.device("cpu"))
    return trainer.job, trainer.phases[-1]


def test_beta_follows_the_predictors_held_out_error():
    job, phase = online_phase("trainer.beta_error_ratio=0.6")
    state = phase.fresh_state(job)
    assert (phase.begin_episode(job, 0, state) == 0).all()
    state["error_first"] = torch.tensor([10.0, 10.0])
    state["error_ema"] = torch.tensor([9.0, 3.0])  # 10 % and 70 % below the first error
    beta = phase.begin_episode(job, 750, state).flatten()
    scheduled = job.actor.inverse_temperature(0.5)
    torch.testing.assert_close(beta, torch.tensor([scheduled * 0.1 / 0.4, scheduled]))


def test_a_memoryless_agent_online_is_algorithm1s_actor_phase(tmp_path):
    """``predictor=none`` under ``trainer=online``: nothing to wait for, so β is the actor's
    schedule and the episodes are, one for one, those of Algorithm 1's actor phase (which a
    memoryless agent enters at once); the pair of commands differs only in the memory."""
    tiny = ["predictor=none", "n_runs=2", "trainer.n_episodes=120", "trainer.final_window=40", "trainer.log_every=40"]
    tiny += ["trainer.checkpoint_every=40", "trainer.td_sample_every=40"]
    results = {}
    for trainer in ("online", "algorithm1"):
        cfg = compose_config(eager([*ONLINE[:1], f"trainer={trainer}", *tiny]))
        results[trainer] = train_job(cfg, tmp_path / trainer)
    episodes = {t: np.load(tmp_path / t / "records" / "episodes.npz") for t in results}
    assert set(episodes["online"].files) == set(episodes["algorithm1"].files)
    for key in episodes["online"].files:
        np.testing.assert_array_equal(episodes["online"][key], episodes["algorithm1"][key], err_msg=key)
    online = np.load(tmp_path / "online" / "records" / "online.npz")
    assert np.isnan(online["prediction_error"]).all()
    job, _ = online_phase("predictor=none")
    scheduled = [job.actor.inverse_temperature(k / 120) for k in range(120)]
    np.testing.assert_allclose(online["beta"], np.broadcast_to(scheduled, (2, 120)), rtol=1e-6)


def test_curiosity_bonus_is_eta_times_the_observation_prediction_error():
    """η_k ρ_y Σ_i |y_i − ŷ_i| at a step, against the predictor's sequence outputs of the same
    history; η anneals linearly to 0 at curiosity_anneal × N."""
    job, phase = online_phase("trainer.curiosity=0.3", "trainer.curiosity_anneal=0.5")
    phase.freeze(job)
    phase.begin_episode(job, 375, phase.fresh_state(job))  # a quarter of N: η halfway annealed
    assert phase.eta_now == pytest.approx(0.15)
    (p,) = job.predictors.values()
    obs = torch.tensor([[0, 2, 3], [1, 2, 2]])  # two runs' observation ids y_0 y_1 y_2
    acts = torch.tensor([[0, 0], [2, 0]])
    state = p.initial_state()
    for t in range(2):
        state = phase.steps_on_ids[0](state, obs[:, t], acts[:, t])
    bonus = phase.reward_bonus(job, [state], obs[:, 2], None, torch.ones(2, dtype=torch.bool))  # exploration=none
    table = job.env.observation_table
    y, a = table[obs].unsqueeze(1), torch.nn.functional.one_hot(acts, 4).float().unsqueeze(1)
    y_hat, _, _ = p.forward_sequences(y, a, torch.full((2, 1), 2))
    want = 0.15 * p.rho_y * (y_hat[:, 0, 2] - y[:, 0, 2]).abs().sum(-1)
    torch.testing.assert_close(bonus, want)


def test_curiosity_off_adds_exactly_zero_whatever_the_error():
    """η = 0 (and η annealed to 0): the bonus is computed, so that one compiled graph serves every η,
    and is exactly 0, also where the observation error is not finite."""
    job, phase = online_phase("trainer.curiosity=0.3", "trainer.curiosity_anneal=0.5")
    phase.freeze(job)
    phase.begin_episode(job, 750, phase.fresh_state(job))  # half of N: η annealed to 0
    (p,) = job.predictors.values()
    state = p.initial_state()
    obs = torch.tensor([2, 3])
    assert phase.reward_bonus(job, [state], obs, None, torch.ones(2, dtype=torch.bool)).tolist() == [0.0, 0.0]
    with torch.no_grad():
        p.b_y.fill_(float("nan"))  # the observation head's output, and so its error, NaN
    assert phase.reward_bonus(job, [state], obs, None, torch.ones(2, dtype=torch.bool)).tolist() == [0.0, 0.0]
    phase.begin_episode(job, 0, phase.fresh_state(job))  # η = 0.3 again: the error reaches the bonus
    assert phase.reward_bonus(job, [state], obs, None, torch.ones(2, dtype=torch.bool)).isnan().all()


def test_sigterm_mid_online_then_resume_equals_uninterrupted(tmp_path, online_run):
    whole, result = online_run
    cut = tmp_path / "cut"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager(ONLINE), f"hydra.run.dir={cut}", "cpu_threads=1"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        found = progress(cut)
        if found is not None and (found["partial"].get("online") or {}).get("episode", 0) >= 300:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=240) == 128 + signal.SIGTERM
    resumed = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            *eager(ONLINE),
            f"hydra.run.dir={cut}",
            "resume=true",
            "cpu_threads=1",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert summary(cut)["metrics"] == result["metrics"]
    for name in ("episodes", "online"):
        got, want = records(cut, name), records(whole, name)
        for key in want:
            if key not in ("predictor_time_s", "actor_time_s"):
                np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}.npz {key}")
