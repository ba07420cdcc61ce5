"""``env.encoding=real``: a ``Box`` observation as real values in [0, 1] (ferl/envs/encodings.py),
each step's vector in a row of its own (ferl/envs/observation_rows.py).

The values are checked against a random-policy sample drawn here with Gymnasium alone and the
formula of the module docstring; the rows against the vectors seen while playing, for the episodes
kept and after they are written over; the online trainer's replay through a resumed run, which
equals the uninterrupted one only if the replayed ids still name the observations they were given
for (the table is in the checkpoint, and the replay wraps round its rows).
"""

import shutil
import sys

import gymnasium
import numpy as np
import pytest
import torch

from conftest import ROOT, compose_config, train_job
from ferl import rng
from ferl.config.params import ConfigError
from ferl.envs.encodings import real_encoder
from ferl.envs.gymnasium_vector import GymnasiumEnv
from ferl.envs.observation_rows import TABLE_BYTES
from ferl.run import checkpoint
from ferl.run.directory import RunDir

sys.path.insert(0, str(ROOT / "tests"))
import stateless_cartpole  # noqa: F401 — registers StatelessCartPole-v0

STATELESS = "stateless_cartpole:StatelessCartPole-v0"


def sample_by_hand(env_id: str, steps: int, limit: int) -> np.ndarray:
    """The set-up sample as ferl/envs/derived.py describes it, written out: seed 0 for the first
    reset and for the actions, uniformly random actions, episodes cut at ``limit`` actions."""
    env = gymnasium.make(env_id)
    env.action_space.seed(0)
    rows, t = [env.reset(seed=0)[0]], 0
    while len(rows) < steps:
        observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows.append(observation)
        t += 1
        if (terminated or truncated or t >= limit) and len(rows) < steps:
            rows.append(env.reset()[0])
            t = 0
    return np.asarray(rows[:steps], np.float64)


def test_real_values_map_the_samples_mean_plus_minus_three_std_onto_0_1():
    env = GymnasiumEnv(3, None, 5, "CartPole-v1", encoding="real", sample_steps=300)
    sample = sample_by_hand("CartPole-v1", 300, env.max_steps)
    mu, sigma = sample.mean(0), sample.std(0)
    np.testing.assert_allclose(env.derived.mean, mu, rtol=1e-12)
    np.testing.assert_allclose(env.derived.std, sigma, rtol=1e-12)
    assert env.observation_size == 4 and env.distinct_codes is None
    seen = env.reset().numpy()
    for r, seed in enumerate(rng.run_seeds(5, 3)):  # each run's first observation, by hand
        x = gymnasium.make("CartPole-v1").reset(seed=seed)[0].astype(np.float64)
        np.testing.assert_allclose(seen[r], np.clip((x - mu) / (6 * sigma) + 0.5, 0, 1), atol=1e-6)
    encode, _ = real_encoder(gymnasium.spaces.Box(-1, 1, (3,)), [0.0, 1.0, 2.0], [1.0, 0.0, 0.5])
    np.testing.assert_allclose(encode([0.6, 7.0, -2.0]), [0.6, 0.5, 0.0])  # ½ + 0.6/6; constant: ½; clipped


def play(env, episodes: int, generator) -> list:
    """(ids, vectors) of every step of every episode played by random actions."""
    out = []
    for _ in range(episodes):
        obs = env.reset()
        steps = [(env.obs_id.clone(), obs.clone())]
        while not bool(env.done.all()):
            obs, *_ = env.step(torch.randint(env.n_actions, (env.n_runs,), generator=generator))
            steps.append((env.obs_id.clone(), obs.clone()))
        out.append(steps)
    return out


def test_ids_name_their_observations_for_the_episodes_kept():
    env = GymnasiumEnv(2, None, 0, STATELESS, encoding="real", sample_steps=200, max_steps=12)
    env.keep_episodes(3, "trainer.replay_episodes")
    assert env.observation_table.shape == (3 * 13 * 2, 2)
    played = play(env, 5, torch.Generator().manual_seed(0))
    for episode in played[2:]:  # the last 3 episodes: each id still names what was seen there
        for ids, vectors in episode:
            torch.testing.assert_close(env.observation_table[ids], vectors, rtol=0, atol=0)
    ids = [{x for i, _ in episode for x in i.tolist()} for episode in played]
    assert not (ids[2] & ids[3]) and not (ids[3] & ids[4]) and not (ids[2] & ids[4])  # none shared
    # episode 0's rows are episode 3's (k mod 3): its first ids now name episode 3's observations
    assert torch.equal(played[0][0][0], played[3][0][0])
    assert not torch.equal(env.observation_table[played[0][0][0]], played[0][0][1])


def test_a_table_too_large_for_the_episodes_kept_is_refused_naming_the_key():
    env = GymnasiumEnv(10, None, 0, STATELESS, encoding="real", sample_steps=100)
    rows_per_episode = (env.max_steps + 1) * 10
    too_many = TABLE_BYTES // (rows_per_episode * env.observation_size * 4) + 1
    with pytest.raises(ConfigError, match=r"^trainer\.replay_episodes: env\.encoding=real keeps a row per step"):
        env.keep_episodes(too_many, "trainer.replay_episodes")
    env.keep_episodes(too_many - 1, "trainer.replay_episodes")  # the largest that fits
    env.reset()
    with pytest.raises(RuntimeError, match="fixed once"):
        env.keep_episodes(2, "trainer.replay_episodes")


@pytest.mark.parametrize(
    "kwargs,says",
    [
        ({"thresholds": [0.0]}, "env.encoding=real encodes"),
        ({"max_observations": 100}, "env.max_observations=100: env.encoding=real"),
        ({"id": "outside_env:CueRecall-v0"}, "is not a Box"),
    ],
)
def test_bad_settings_of_real_say_which(kwargs, says):
    sys.path.insert(0, str(ROOT / "tests"))
    with pytest.raises(ConfigError, match=says):
        GymnasiumEnv(1, None, 0, **{"id": STATELESS, "encoding": "real", **kwargs})


ONLINE = [
    "experiment=none",
    "env=gymnasium",
    f"env.id={STATELESS}",
    "env.encoding=real",
    "env.sample_steps=200",
    "env.max_steps=20",
    "actor=ferl_tmaze",
    "predictor=joint_scalar",
    "trainer=online",
    "trainer.n_episodes=24",
    "trainer.replay_episodes=5",
    "trainer.replay_sample=4",
    "trainer.replay_batch_size=2",
    "trainer.checkpoint_every=8",
    "trainer.log_every=8",
    "trainer.final_window=8",
    "n_runs=2",
]


def test_the_online_replay_of_real_values_resumes_as_uninterrupted(tmp_path):
    """An LSTM predictor learns online from real values; from the checkpoint at episode 16 (its
    replay of 5 episodes has wrapped round the rows twice), resume=true ends as the whole run."""
    whole_dir, cut = tmp_path / "whole", tmp_path / "cut"
    whole = train_job(compose_config(ONLINE), whole_dir)
    RunDir(whole_dir).write_summary(whole)
    shutil.copytree(whole_dir, cut)
    (cut / "summary.json").unlink()
    shutil.move(cut / "checkpoints" / checkpoint.PREVIOUS, cut / "checkpoints" / checkpoint.LAST)
    saved = checkpoint.read(cut / "checkpoints" / checkpoint.LAST).state()
    assert saved["progress"]["partial"]["online"]["episode"] == 16
    assert saved["env"]["table"].shape == (6 * 21 * 2, 2)  # K + 1 episodes of T_max + 1 steps, 2 runs
    resumed = train_job(compose_config(ONLINE), cut, resume=True)
    assert resumed["metrics"] == whole["metrics"]
    online = [np.load(d / "records" / "online.npz") for d in (whole_dir, cut)]
    np.testing.assert_array_equal(online[0]["prediction_error"], online[1]["prediction_error"])
    assert np.isfinite(online[0]["prediction_error"]).all()


def test_every_replayed_id_names_the_observation_of_the_episode_it_was_stored_with(tmp_path, monkeypatch):
    """A ledger of the episode that last wrote every row (``StepRows.place``) and of the episode
    stored in every replay slot (``store_episode``): each id the online trainer's replay reads
    (``stored_episodes``) was last written by the episode stored where it was drawn."""
    import ferl.trainers.online_episodes as online
    from ferl.envs.observation_rows import StepRows

    written: dict[int, int] = {}  # row id → episode that last wrote it
    slots: dict[int, int] = {}  # replay slot → episode stored there
    reads = []
    place, store, stored = StepRows.place, online.store_episode, online.stored_episodes

    def placing(self, values, episode, t, runs):
        ids = place(self, values, episode, t, runs)
        written.update({i: episode for i in ids[runs].tolist()})
        return ids

    def storing(replay, count, episode):
        slots[count % next(iter(replay.values())).shape[1]] = count
        return store(replay, count, episode)

    def reading(replay, index):
        out = stored(replay, index)
        for r in range(index.shape[0]):
            for n, slot in enumerate(index[r].tolist()):
                ids = out["obs"][r, n]
                reads.append({written[i] for i in ids[ids >= 0].tolist()} == {slots[slot]})
        return out

    monkeypatch.setattr(StepRows, "place", placing)
    monkeypatch.setattr(online, "store_episode", storing)
    monkeypatch.setattr(online, "stored_episodes", reading)
    train_job(compose_config([*ONLINE, "trainer.checkpoint_every=100"]), tmp_path / "run")
    assert len(reads) == 24 * 2 * 4 and all(reads)  # episodes × runs × replayed episodes
