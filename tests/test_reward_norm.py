"""A scalar reward head that learns each run's standardised reward (``reward_norm=popart``,
ferl/predictors/popart.py; van Hasselt et al. 2016), so that an outside environment is learnt at
its own reward scale (docs/beyond.md, "Reward scale").

The statistics are checked against numpy over the same rewards; the head's rescaling against its
outputs before and after; the whole route against the delayed-recall environment of
tests/outside_env.py at its native scale (rewards −0.1 and ±1, ``env.reward_scale=1``), which FERL
trained online does not learn without the normalisation (2/10 runs at the optimum, 9/10 with it:
docs/beyond.md). A constant reward (CartPole's +1 a step), whose σ vanishes, is learnt as without
the normalisation: the same runs, step for step.
"""

import sys

import numpy as np
import pytest
import torch

from conftest import ROOT, compose_config, train_job
from ferl.predictors.popart import RewardStatistics, normalised
from ferl.predictors.recurrent import predictor

sys.path.insert(0, str(ROOT / "tests"))
# CueRecall's optimum: two blank steps (−0.1 each), then the cue recalled (+1)
# the groups' own defaults, as a new environment gets them (docs/beyond.md, "Reward scale"): reward_scale 1 and
# predictor=joint_scalar's PopArt; γ = 0.5 as the card games (the setting measured with 10 runs there)
NATIVE = [
    "experiment=none",
    "env=gymnasium",
    "predictor=joint_scalar",
    "actor=ferl_tmaze",
    "trainer=online",
    "env.id=outside_env:CueRecall-v0",
    "env.kwargs={delay:2}",
    "env.optimal_return=0.8",
    "actor.gamma=0.5",
    "trainer.n_episodes=2000",
    "trainer.replay_sample=16",
    "trainer.log_every=500",
    "trainer.checkpoint_every=100000",
    "n_runs=3",
]


# CartPole: +1 at every step, a constant reward; a thermometer code per entry of its Box
CONSTANT = [
    "experiment=popgym_repeat_previous_easy",
    "env.id=CartPole-v1",
    "env.thresholds=[[-1,0,1],[-1,0,1],[-0.1,0,0.1],[-1,0,1]]",
    "env.reward_scale=1",
    "env.optimal_return=null",
    "actor.gamma=0.9",
    "trainer.n_episodes=40",
    "trainer.log_every=20",
    "trainer.checkpoint_every=100000",
    "n_runs=2",
]


def test_statistics_are_the_moments_of_every_reward_seen():
    g = torch.Generator().manual_seed(0)
    stats, seen = RewardStatistics(2), [[], []]
    for _ in range(4):
        rewards = torch.randn(2, 3, 5, generator=g) * torch.tensor([0.02, 7.0]).view(2, 1, 1) + 1.5
        lengths = torch.randint(1, 6, (2, 3), generator=g)
        mask = torch.arange(5) < lengths.unsqueeze(-1)
        stats.update(rewards, mask)
        for r in range(2):
            seen[r] += rewards[r][mask[r]].tolist()
    mu, sigma = stats.moments()
    np.testing.assert_allclose(mu.numpy(), [np.mean(s) for s in seen], rtol=1e-5)
    np.testing.assert_allclose(sigma.numpy(), [np.std(s) for s in seen], rtol=1e-5)
    z = normalised(stats, torch.tensor([[1.5], [8.5]]))
    np.testing.assert_allclose(z.numpy().ravel(), [(1.5 - mu[0]) / sigma[0], (8.5 - mu[1]) / sigma[1]], rtol=1e-5)


def test_head_outputs_in_the_environments_units_are_preserved():
    p = predictor(
        memory="lstm", n_runs=2, n_obs=4, n_actions=2, reward_output="linear", n_reward=1, reward_norm="popart"
    )
    y, a = torch.rand(2, 3, 5, 4).round(), torch.nn.functional.one_hot(torch.randint(2, (2, 3, 4)), 2).float()
    lengths = torch.tensor([[4, 2, 3], [1, 4, 4]])

    def in_env_units():
        mu, sigma = p.reward_stats.moments()
        return p.forward_sequences(y, a, lengths)[1] * sigma.view(2, 1, 1, 1) + mu.view(2, 1, 1, 1)

    for scale in (1 / 48, 30.0):
        before = in_env_units()
        p.observe_rewards(torch.randn(2, 3, 4) * scale - 0.3, lengths)
        torch.testing.assert_close(in_env_units(), before, rtol=1e-4, atol=1e-4 * scale)
    assert p.describe()["reward_norm"] == "popart"


def test_off_by_default_and_only_for_a_scalar_reward():
    assert predictor(memory="elman", n_runs=1, n_obs=3, n_actions=2, n_reward=4).reward_stats is None
    with pytest.raises(ValueError, match=r"reward_norm=.popart. is not allowed"):
        predictor(
            memory="elman", n_runs=1, n_obs=3, n_actions=2, reward_output="bits", n_reward=4, reward_norm="popart"
        )


def test_native_scale_delayed_recall_is_learnt_online(tmp_path):
    """Acceptance: FERL online, CueRecall at reward_scale=1: ≥ 2 of 3 runs at the optimum."""
    summary = train_job(compose_config(NATIVE), tmp_path / "run")
    final = np.array(summary["metrics"]["final_return"])
    assert summary["optimal"]["return"] == pytest.approx(0.8)
    assert (final >= 0.95 * 0.8).sum() >= 2, final


def test_rewards_that_have_not_varied_are_not_divided_by_their_vanishing_sigma():
    """Equal rewards: the identity, (μ, σ) = (0, 1), whatever their value; the first reward that
    differs switches to the standardised reward with the head's outputs preserved."""
    p = predictor(
        memory="lstm", n_runs=2, n_obs=4, n_actions=2, reward_output="linear", n_reward=1, reward_norm="popart"
    )
    lengths = torch.tensor([[4, 2, 3], [1, 4, 4]])
    constant = torch.tensor([1.0, 48.0]).view(2, 1, 1).expand(2, 3, 4)
    p.observe_rewards(constant, lengths)
    mu, sigma = p.reward_stats.moments()
    assert mu.tolist() == [0.0, 0.0] and sigma.tolist() == [1.0, 1.0]
    torch.testing.assert_close(normalised(p.reward_stats, constant), constant, rtol=0, atol=0)
    y, a = torch.rand(2, 3, 5, 4).round(), torch.nn.functional.one_hot(torch.randint(2, (2, 3, 4)), 2).float()
    before = p.forward_sequences(y, a, lengths)[1]  # in the environment's units while (μ, σ) = (0, 1)
    p.observe_rewards(constant + torch.tensor([0.5, -3.0]).view(2, 1, 1), lengths)
    mu, sigma = p.reward_stats.moments()
    assert (sigma > 0.1).all()  # now standardised: σ of the rewards seen, as numpy has it
    np.testing.assert_allclose(sigma.numpy()[0], np.std([1.0] * 9 + [1.5] * 9), rtol=1e-5)
    after = p.forward_sequences(y, a, lengths)[1] * sigma.view(2, 1, 1, 1) + mu.view(2, 1, 1, 1)
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-3)


def test_a_constant_reward_is_learnt_as_without_normalisation(tmp_path):
    """PopArt on CartPole's constant reward: the runs and their prediction errors are those of
    ``reward_norm=none`` (the same seeds), not errors of ~1/σ that exploration would then chase."""
    runs, errors = {}, {}
    for norm in ("popart", "none"):
        runs[norm] = train_job(compose_config([*CONSTANT, f"predictor.joint.reward_norm={norm}"]), tmp_path / norm)
        errors[norm] = np.load(tmp_path / norm / "records" / "online.npz")["prediction_error"]
    assert np.isfinite(errors["none"]).all() and errors["none"].shape == (2, 40)
    np.testing.assert_allclose(errors["popart"], errors["none"], rtol=1e-5, atol=1e-6)
    assert runs["popart"]["metrics"]["final_return"] == runs["none"]["metrics"]["final_return"]
