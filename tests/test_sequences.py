"""Random-policy episodes, length balancing and the train/test split (§4.3.1)."""

import torch

from ferl.envs.tmaze import TMaze
from ferl.trainers.episodes import balance_and_split, collect_random_episodes
from ferl.trainers.handoffs import Episodes


def collect(R=3, n=600, copies=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    env = TMaze(R * copies, g, corridor_length=3, max_steps=10, matching=True)
    return collect_random_episodes(env, n, R, g), env


def test_collected_episodes_are_consistent():
    ep, env = collect()
    assert ep.lengths.shape == (3, 600)
    assert ((ep.lengths >= 3) & (ep.lengths <= 10)).all()
    t = torch.arange(11)
    observed = ep.obs >= 0
    assert torch.equal(observed, t <= ep.lengths.unsqueeze(-1))  # y_0 … y_T, padding after
    # an episode that ends before T_max ends in a goal (observation ids of the two goals)
    goal_ids = {env.observation_names.index("goal_left"), env.observation_names.index("goal_right")}
    last = ep.obs.gather(2, ep.lengths.unsqueeze(-1)).squeeze(-1)
    short = ep.lengths < 10
    assert all(int(i) in goal_ids for i in last[short])
    assert set(ep.rewards[short].gather(-1, (ep.lengths[short] - 1).unsqueeze(-1)).flatten().tolist()) <= {5.0, -5.0}


def test_random_lengths_follow_the_random_policy():
    """P(T = 3) for a random walker: N, N, then E or W = (1/4)(1/4)(2/4) = 1/32."""
    ep, _ = collect(R=2, n=4000)
    p3 = (ep.lengths == 3).float().mean().item()
    assert abs(p3 - 1 / 32) < 0.008


def test_balanced_and_disjoint_split():
    """Episodes carry their index as y_0, so train and test can be checked for overlap exactly."""
    R, N = 3, 900
    g = torch.Generator().manual_seed(1)
    lengths = torch.randint(3, 11, (R, N), generator=g)
    obs = torch.zeros(R, N, 11, dtype=torch.long)
    obs[:, :, 0] = torch.arange(N)
    ep = Episodes(obs, torch.zeros(R, N, 10, dtype=torch.long), torch.zeros(R, N, 10), lengths)
    train, test, (n_train, n_test) = balance_and_split(ep, 3, 10, 0.8, g)
    n = int(torch.stack([(lengths == T).sum(1) for T in range(3, 11)]).min())
    assert (n_train, n_test) == (round(0.8 * n), n - round(0.8 * n))
    for T in range(3, 11):
        assert ((train.lengths == T).sum(1) == n_train).all()
        assert ((test.lengths == T).sum(1) == n_test).all()
    for r in range(R):
        train_ids, test_ids = set(train.obs[r, :, 0].tolist()), set(test.obs[r, :, 0].tolist())
        assert len(train_ids) == train.obs.shape[1] and len(test_ids) == test.obs.shape[1]
        assert not train_ids & test_ids
        # every selected episode keeps its own length
        assert torch.equal(train.lengths[r], lengths[r, train.obs[r, :, 0]])
