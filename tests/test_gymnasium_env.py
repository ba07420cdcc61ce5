"""Third-party Gymnasium environments as ferl environments (issue 5/8, CONTRACT §2 ``env=gymnasium``).

The encodings are checked against Gymnasium's own ``spaces.flatten`` (one-hot for discrete spaces)
and against loops written out; the vector of environments against single environments stepped
by hand with Gymnasium's next-step auto-reset; the whole path through train.py and analyze.py on
the environment of tests/outside_env.py, which nothing in ferl names.
"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import ROOT, compose_config, eager, run_train, train_job
from ferl.envs.encodings import MINIGRID_SIZES, NoEncoding, encoder_for
from ferl.envs.gymnasium_vector import GymnasiumEnv
from ferl.interfaces import EpisodicEnvironment
from test_tmaze_resume import progress

TESTS = ROOT / "tests"
CUE = "outside_env:CueRecall-v0"
ENV = {**os.environ, "PYTHONPATH": str(TESTS)}
sys.path.insert(0, str(TESTS))
# FERL trained online (§5.4) on the cue task: a POPGym experiment with its environment swapped, its
# rewards ×5 for predictor and actor and the predictor's reward unnormalised, which learns in 1 000
# episodes (tests/test_reward_norm.py learns the native scale, normalised, in 2 000)
RUN = [
    "experiment=popgym_repeat_previous_easy",
    f"env.id={CUE}",
    "+env.kwargs.delay=2",
    "env.optimal_return=0.8",
    "env.reward_scale=5",
    "predictor.joint.reward_norm=none",
    "trainer.n_episodes=1000",
    "trainer.replay_sample=16",
    "trainer.log_every=100",
    "trainer.checkpoint_every=100",
    "n_runs=3",
]


@pytest.mark.parametrize(
    "space",
    [
        spaces.Discrete(5),
        spaces.Discrete(4, start=-2),
        spaces.MultiDiscrete([3, 2, 4]),
        spaces.MultiDiscrete([[2, 3], [4, 2]]),
        spaces.MultiBinary(6),
        spaces.Tuple((spaces.Discrete(3), spaces.MultiDiscrete([2, 5]))),
        spaces.Dict({"b": spaces.Discrete(2), "a": spaces.Tuple((spaces.Discrete(3), spaces.MultiBinary(2)))}),
    ],
)
def test_onehot_is_gymnasiums_flattening(space):
    encode, size = encoder_for(space, "auto")
    assert size == spaces.flatdim(space)
    space.seed(0)
    for _ in range(50):
        x = space.sample()
        np.testing.assert_array_equal(encode(x), spaces.flatten(space, x).astype(np.uint8))


def test_thresholds_are_a_thermometer_code():
    space, theta = spaces.Box(-1, 1, (2, 3)), [-0.5, 0.0, 0.5]
    encode, size = encoder_for(space, "thresholds", theta)
    x = np.array([[-0.9, -0.2, 0.1], [0.7, 0.5, -0.5]], np.float32)
    want = [int(v > t) for v in x.reshape(-1) for t in theta]
    assert size == 18 and encode(x).tolist() == want


def test_minigrid_view_is_one_hot_per_cell():
    space = spaces.Dict({"direction": spaces.Discrete(4), "image": spaces.Box(0, 255, (7, 7, 3), np.uint8)})
    encode, size = encoder_for(space, "auto")
    assert size == 49 * sum(MINIGRID_SIZES)
    rng = np.random.default_rng(0)
    image = np.stack([rng.integers(0, n, (7, 7)) for n in MINIGRID_SIZES], -1)
    bits = encode({"direction": 1, "image": image}).reshape(7, 7, -1)
    for i in range(7):
        for j in range(7):
            want = np.concatenate([np.eye(n, dtype=np.uint8)[image[i, j, k]] for k, n in enumerate(MINIGRID_SIZES)])
            np.testing.assert_array_equal(bits[i, j], want)


def test_a_box_has_no_automatic_encoding():
    with pytest.raises(NoEncoding, match="Box"):
        encoder_for(spaces.Box(-1, 1, (3,)), "auto")


def reference_runs(n_runs, seed, kwargs, actions_per_step):
    """Single CueRecall environments stepped as Gymnasium's next-step auto-reset steps them in a
    vector, with ferl's lockstep: (rewards, dones, encoded observations) per lockstep step."""
    import gymnasium

    envs = [gymnasium.make(CUE, **kwargs) for _ in range(n_runs)]
    encode, _ = encoder_for(envs[0].observation_space, "onehot")
    out, obs, seeded = [], [None] * n_runs, False
    for episode in actions_per_step:
        obs = [encode(e.reset(seed=seed + r if not seeded else None)[0]) for r, e in enumerate(envs)]
        seeded, done, auto_reset = True, [False] * n_runs, [False] * n_runs
        for actions in episode:
            rewards, dones, seen = [], [], []
            for r, e in enumerate(envs):
                if auto_reset[r]:  # the step after an episode's end resets it (next-step auto-reset)
                    e.reset()
                    auto_reset[r], o, rew, term, trunc = False, None, 0.0, False, False
                else:
                    o, rew, term, trunc, _ = e.step(0 if done[r] else int(actions[r]))
                    auto_reset[r] = term or trunc
                if not done[r]:
                    obs[r] = encode(o)
                    done[r] = term or trunc
                    rewards.append(rew)
                else:
                    rewards.append(0.0)
                dones.append(done[r])
                seen.append(obs[r])
            out.append((rewards, dones, np.stack(seen)))
            if all(done):
                break
    return out


def test_vector_steps_as_single_environments_in_lockstep():
    kwargs = {"delay": 3, "random_delay": True}
    env = GymnasiumEnv(4, None, 7, CUE, kwargs=kwargs)
    assert isinstance(env, EpisodicEnvironment) and env.max_steps == 10 and env.observation_size == 5
    rng = np.random.default_rng(1)
    plan = [[rng.integers(2, size=4) for _ in range(env.max_steps)] for _ in range(6)]
    want = iter(reference_runs(4, 7, kwargs, plan))
    lengths = set()
    for episode in plan:
        env.reset()
        for actions in episode:
            _, reward, _, _ = env.step(torch.as_tensor(actions))
            rewards, dones, seen = next(want)
            np.testing.assert_allclose(reward.numpy(), rewards, atol=1e-7)
            assert env.done.tolist() == dones
            np.testing.assert_array_equal(env.observe().numpy(), seen)
            if bool(env.done.all()):
                break
        lengths |= set(env.t.tolist())
    assert len(lengths) > 1  # runs did wait for each other


def test_multidiscrete_actions_are_enumerated():
    env = GymnasiumEnv(5, None, 0, CUE, kwargs={"delay": 1, "grid_actions": True})
    assert env.n_actions == 6 and env.action_names[4] == "(1,1)"
    cue = env.reset()[:, :2].argmax(1)  # the cue's one-hot bits
    env.step(torch.zeros(5, dtype=torch.long))
    _, reward, terminated, _ = env.step(cue * 3 + 2)  # action i = (i // 3, i % 3): the first entry chooses
    assert terminated.all() and (reward == 1).all() and (env.outcomes()["return"] == pytest.approx(0.9))


def test_state_dict_resumes_the_same_episodes():
    kwargs = {"delay": 3, "random_delay": True}
    a, b = GymnasiumEnv(3, None, 0, CUE, kwargs=kwargs), GymnasiumEnv(3, None, 99, CUE, kwargs=kwargs)
    g = torch.Generator().manual_seed(0)
    a.reset()
    a.step(torch.randint(2, (3,), generator=g))
    b.load_state_dict(a.state_dict())
    for _ in range(4):
        a.reset(), b.reset()
        for _ in range(a.max_steps):
            action = torch.randint(2, (3,), generator=g)
            for x, y in zip(a.step(action), b.step(action)):
                torch.testing.assert_close(x, y, rtol=0, atol=0)
    assert a.observation_names == b.observation_names


@pytest.fixture(scope="module")
def cue_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("cue") / "run"
    result = run_train(*RUN, f"hydra.run.dir={run_dir}", env=ENV)
    assert result.returncode == 0, result.stderr[-3000:]
    (run_dir.parent / "stderr.txt").write_text(result.stderr)  # the progress bars
    return run_dir


def test_trains_and_analyses_end_to_end(cue_run):
    summary = json.loads((cue_run / "summary.json").read_text())
    manifest = json.loads((cue_run / "records" / "run.json").read_text())
    assert summary["task"] == manifest["task"] == "gymnasium" and manifest["env"]["id"] == CUE
    metrics = summary["metrics"]
    assert {"final_return", "env_steps_total", "solved"} <= set(metrics)
    # β's schedule as the config gives it, for analysis to tell a random policy (β = 0) apart
    beta = compose_config(RUN).actor.beta
    assert manifest["actor"]["beta"] == {"start": beta.start, "end": beta.end}
    # named for what the environment records: it has no goal, so no steps to one
    assert "final_steps_to_goal" not in metrics and "steps_to_goal" not in summary["optimal"]
    assert metrics["env_steps_total"] == [3000] * 3  # 1 000 episodes of 3 steps
    episodes = np.load(cue_run / "records" / "episodes.npz")
    np.testing.assert_allclose(episodes["return"][:, -200:].mean(1), metrics["final_return"], rtol=1e-6)
    # a memoryless agent is right half the time at the choice: return −0.2 + 0 on average
    assert min(metrics["final_return"]) > 0.4, metrics["final_return"]
    result = subprocess.run(
        [sys.executable, str(ROOT / "analyze.py"), str(cue_run)], capture_output=True, text=True, timeout=300, env=ENV
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "learning_curves" in {p.stem for p in (cue_run / "analysis").glob("*.png")}
    # a task of one's own: a plain report, no claims section, no word of the dissertation
    report = (cue_run / "analysis" / "report.md").read_text()
    assert report.startswith("# Report: popgym_repeat_previous_easy (task `gymnasium`)")
    assert "## Claims" not in report and "dissertation" not in report and "steps_to_goal" not in report


def test_the_progress_bar_names_the_discounted_and_the_undiscounted_return(cue_run):
    """The bar's discounted return is `disc_return_ma200`; the undiscounted one, what
    `final_return` reports, is `return_ma200` beside it (×5 reward scale aside, their last values
    are the records' means over the last 200 episodes)."""
    last = (cue_run.parent / "stderr.txt").read_text().replace("\r", "\n").splitlines()
    bar = [line for line in last if "disc_return_ma200=" in line][-1]  # tqdm: [time, rate, postfix]
    postfix = bar[bar.index("disc_return_ma200=") :].rstrip().rstrip("]")
    shown = dict(item.split("=") for item in postfix.split(", "))
    episodes = np.load(cue_run / "records" / "episodes.npz")
    assert float(shown["disc_return_ma200"]) == pytest.approx(episodes["discounted_return"][:, -200:].mean(), abs=1e-3)
    assert float(shown["return_ma200"]) == pytest.approx(episodes["return"][:, -200:].mean(), abs=1e-3)


def test_same_seed_same_numbers_sync_and_async(tmp_path):
    short = [*RUN[:-3], "trainer.n_episodes=40", "n_runs=2"]
    runs = [
        train_job(compose_config([*short, *extra]), tmp_path / name)["metrics"]
        for name, extra in (("a", []), ("b", []), ("c", ["env.vectorization=async"]))
    ]
    assert runs[0] == runs[1] == runs[2]


def test_sigterm_then_resume_equals_uninterrupted(tmp_path, cue_run):
    cut = tmp_path / "cut"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *eager(RUN), f"hydra.run.dir={cut}"],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        saved = progress(cut)
        if saved is not None and (saved["partial"].get("online") or {}).get("episode", 0) >= 200:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=240) == 128 + signal.SIGTERM
    assert 0 < progress(cut)["partial"]["online"]["episode"] < 1000
    result = run_train(*RUN, "resume=true", f"hydra.run.dir={cut}", env=ENV)
    assert result.returncode == 0, result.stderr[-2000:]
    got, want = (json.loads((d / "summary.json").read_text())["metrics"] for d in (cut, cue_run))
    assert got == want
    for key in ("return", "discounted_return", "steps"):
        np.testing.assert_array_equal(
            np.load(cut / "records" / "episodes.npz")[key], np.load(cue_run / "records" / "episodes.npz")[key]
        )


@pytest.mark.parametrize(
    "override, names",
    [
        ("env.id=outside_env:Nope-v0", "env.id"),
        ("env.id=nowhere:Cue-v0", "env.id"),
        ("env.id=Pendulum-v1", "action space Box"),
        # a Box has no one-hot code (with no encoding named, its thresholds are derived: tests/test_box_encodings.py)
        ("env.id=CartPole-v1 env.encoding=onehot", "observation space"),
        # Algorithm 1's predictors need the observation table before the episodes
        (f"env.id={CUE} trainer=algorithm1", "trainer=online, or predictor=none"),
    ],
)
def test_bad_input_one_line_nothing_written(tmp_path, override, names):
    run_dir = tmp_path / "out" / "run"
    result = run_train(RUN[0], *override.split(), f"hydra.run.dir={run_dir}", env=ENV)
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1 and lines[0].startswith("ferl: error:"), result.stderr
    assert names in lines[0]
    assert not (tmp_path / "out").exists()
