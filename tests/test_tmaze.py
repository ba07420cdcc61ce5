"""T-mazes (§4.3.1–4.3.3): moves, walls, goals, signals, truncation, optimal return, images."""

import pytest
import torch

from ferl.envs.tmaze import TMaze

N, E, S, W = range(4)
START, CORRIDOR, JUNCTION, LEFT, RIGHT, SIG0, SIG1 = range(7)


def make_env(R=1, seed=0, **kw):
    return TMaze(R, torch.Generator().manual_seed(seed), **kw)


def act(env, a):
    return env.step(torch.full((env.n_runs,), a, dtype=torch.long))


def set_signals(env, s0, s1=None):
    full = lambda v: torch.full((env.n_runs,), v, dtype=torch.long)  # noqa: E731
    env.set_signals(full(s0), None if s1 is None else full(s1))


def bits(obs):
    """Indices of the set bits of a single-run observation."""
    return torch.nonzero(obs[0]).squeeze(1).tolist()


def test_corridor_moves_up_and_back_down():
    env = make_env(corridor_length=4)
    env.reset()
    for expected in (1, 2, 3):
        obs, r, term, trunc = act(env, N)
        assert env.position.item() == expected and r.item() == pytest.approx(-0.1)
        assert not term.item() and not trunc.item()
    assert bits(obs) == [JUNCTION] and env.at_junction.item()
    for expected in (2, 1, 0):
        obs, r, _, _ = act(env, S)
        assert env.position.item() == expected and r.item() == pytest.approx(-0.1)
    assert bits(obs)[0] == START and not env.at_junction.item()
    assert env.t.item() == 6


@pytest.mark.parametrize("position,action", [(0, S), (0, E), (0, W), (1, E), (1, W), (2, N)])
def test_wall_bumps_cost_one_and_do_not_move(position, action):
    env = make_env(corridor_length=3)
    before = env.reset()
    for _ in range(position):
        before, _, _, _ = act(env, N)
    obs, r, term, trunc = act(env, action)
    assert r.item() == -1.0 and env.position.item() == position
    assert torch.equal(obs, before) and not term.item() and not trunc.item()


@pytest.mark.parametrize("s0", [0, 1])
@pytest.mark.parametrize("action", [E, W])
def test_regular_goals(s0, action):
    env = make_env(corridor_length=3)
    env.reset()
    set_signals(env, s0)
    act(env, N), act(env, N)
    obs, r, term, trunc = act(env, action)
    right = action == E
    assert r.item() == (5.0 if right == bool(s0) else -5.0)
    assert term.item() and not trunc.item() and env.done.item()
    assert env.correct.item() == (right == bool(s0))
    assert env.rewarded_goal.item() == 3 + s0 and env.condition.item() == s0
    assert bits(obs) == [RIGHT if right else LEFT] and env.position.item() == (4 if right else 3)


@pytest.mark.parametrize("s0,s1", [(0, 0), (0, 1), (1, 0), (1, 1)])
@pytest.mark.parametrize("action", [E, W])
def test_matching_goals(s0, s1, action):
    env = make_env(corridor_length=3, matching=True)
    env.reset()
    set_signals(env, s0, s1)
    act(env, N)
    obs, _, _, _ = act(env, N)
    assert bits(obs) == [JUNCTION, SIG0 + s1]
    _, r, term, _ = act(env, action)
    rewarded_right = s0 == s1
    assert r.item() == (5.0 if (action == E) == rewarded_right else -5.0) and term.item()
    assert env.rewarded_goal.item() == 3 + rewarded_right and env.condition.item() == 2 * s0 + s1


@pytest.mark.parametrize("matching", [False, True])
def test_signals_visible_only_where_specified(matching):
    env = make_env(R=64, seed=3, corridor_length=4, matching=matching)
    obs = env.reset()
    assert torch.equal(obs[:, SIG0:].argmax(1), env.initial_signal) and (obs[:, SIG0:].sum(1) == 1).all()
    assert (obs[:, START] == 1).all() and obs.sum(1).eq(2).all()
    for _ in range(2):  # plain corridor cells: no signal
        obs, _, _, _ = act(env, N)
        assert (obs[:, CORRIDOR] == 1).all() and obs.sum(1).eq(1).all()
    obs, _, _, _ = act(env, N)
    assert (obs[:, JUNCTION] == 1).all()
    if matching:
        assert torch.equal(obs[:, SIG0:].argmax(1), env.junction_signal) and obs.sum(1).eq(2).all()
    else:
        assert obs.sum(1).eq(1).all() and (env.junction_signal == -1).all()
    obs, _, _, _ = act(env, E)
    assert (obs[:, RIGHT] == 1).all() and obs.sum(1).eq(1).all()


def test_truncation_and_done_runs_stay_frozen():
    env = make_env(R=2, corridor_length=3, max_steps=5)
    env.reset()
    for _ in range(4):  # run 0 bumps S at the start, run 1 walks up and bumps N at the junction
        _, _, term, trunc = env.step(torch.tensor([S, N]))
        assert not term.any() and not trunc.any()
    _, r, term, trunc = act(env, S)
    assert trunc.all() and not term.any() and env.done.all() and (env.t == 5).all()
    frozen = (env.observe(), env.position.clone(), env.t.clone())
    obs, r, term, trunc = env.step(torch.tensor([N, W]))  # W at the junction would enter a goal
    assert (r == 0).all() and not term.any() and not trunc.any()
    assert torch.equal(obs, frozen[0]) and torch.equal(env.position, frozen[1]) and torch.equal(env.t, frozen[2])
    assert (env.reward_code(r) == 0).all()


def test_terminated_run_frozen_while_others_continue():
    env = make_env(R=2, corridor_length=2)
    env.reset()
    set_signals(env, 1)
    act(env, N)
    _, r, term, _ = env.step(torch.tensor([E, N]))
    assert term.tolist() == [True, False] and r.tolist() == [5.0, -1.0]
    _, r, term, _ = env.step(torch.tensor([W, W]))
    assert r.tolist() == [0.0, -5.0] and term.tolist() == [False, True] and env.position.tolist() == [3, 2]
    assert env.correct.tolist() == [True, False] and env.t.tolist() == [2, 3]


@pytest.mark.parametrize("T", [2, 3, 6])
@pytest.mark.parametrize("matching", [False, True])
def test_shortest_path_takes_T_min_actions(T, matching):
    env = make_env(R=8, seed=T, corridor_length=T, max_steps=T, matching=matching)
    env.reset()
    for _ in range(T - 1):
        _, _, term, trunc = act(env, N)
        assert not term.any() and not trunc.any()
    assert env.at_junction.all()
    correct_action = torch.where(env.rewarded_goal == T + 1, E, W)
    _, r, term, trunc = env.step(correct_action)
    assert term.all() and not trunc.any() and (r == 5.0).all() and env.correct.all()
    assert (env.t == T).all() and env.optimal_steps == T


@pytest.mark.parametrize("T", [2, 3, 6])
def test_optimal_discounted_return(T):
    gamma = 0.95
    closed_form = sum(-0.1 * gamma**k for k in range(T - 1)) + 5 * gamma ** (T - 1)
    for matching in (False, True):
        for max_steps in (T, 10):  # T_max = T_min leaves exactly the shortest path
            env = make_env(corridor_length=T, max_steps=max(max_steps, T), matching=matching)
            assert env.optimal_discounted_return(gamma) == pytest.approx(closed_form)
    if T == 3:
        assert closed_form == pytest.approx(4.3175)


def test_signals_uniform_over_many_runs():
    env = make_env(R=40_000, seed=5, matching=True)
    env.reset()
    counts = torch.bincount(env.condition, minlength=4).float() / env.n_runs
    assert torch.allclose(counts, torch.full((4,), 0.25), atol=0.015)
    regular = make_env(R=40_000, seed=6)
    assert abs(regular.initial_signal.float().mean().item() - 0.5) < 0.015


def test_reward_code_one_hot():
    env = make_env()
    assert env.reward_values == pytest.approx((-5.0, -1.0, -0.1, 5.0))
    code = env.reward_code(torch.tensor([-5.0, -1.0, -0.1, 5.0, 0.0]))
    assert torch.equal(code, torch.cat([torch.eye(4), torch.zeros(1, 4)]))


def test_observed_reward_is_encoded():
    env = make_env(corridor_length=2)
    env.reset()
    set_signals(env, 0)
    codes = [env.reward_code(act(env, a)[1])[0].argmax().item() for a in (S, N, E)]
    assert codes == [1, 2, 0]  # wall −1, step −0.1, wrong goal −5


def test_reproducible_with_seed_and_state_dict_resume():
    def rollout(env, actions):
        return torch.stack([torch.cat([o.flatten(), r]) for o, r, _, _ in (env.step(a) for a in actions)])

    actions = torch.randint(4, (12, 50), generator=torch.Generator().manual_seed(9))
    a, b = make_env(R=50, seed=1, matching=True), make_env(R=50, seed=1, matching=True)
    assert torch.equal(rollout(a, actions), rollout(b, actions))
    assert torch.equal(a.reset(), b.reset()) and torch.equal(a.condition, b.condition)
    assert not torch.equal(make_env(R=50, seed=2, matching=True).condition, b.condition)

    env = make_env(R=50, seed=4, matching=True)
    rollout(env, actions[:3])
    state = env.state_dict()
    rest = rollout(env, actions[3:])
    resumed = make_env(R=50, seed=99, matching=True)
    resumed.load_state_dict(state)
    assert torch.equal(rollout(resumed, actions[3:]), rest)


@pytest.mark.parametrize(
    "kw,key", [({"corridor_length": 1}, "^corridor_length=1"), ({"corridor_length": 4, "max_steps": 3}, "^max_steps=3")]
)
def test_invalid_sizes_raise(kw, key):
    with pytest.raises(ValueError, match=key):
        make_env(**kw)


def test_images_replace_observations():
    names = ("start_0", "start_1", "corridor", "junction_0", "junction_1", "goal_left", "goal_right")
    images = {n: torch.full((784,), i / 10) for i, n in enumerate(names)}
    env = make_env(R=4, matching=True, images=images)
    assert env.observation_size == 784 and env.observation_names == names
    obs = env.reset()
    assert obs.shape == (4, 784)
    assert torch.allclose(obs[:, 0], env.initial_signal.float() / 10)
    act(env, N)
    obs, _, _, _ = act(env, N)
    assert torch.allclose(obs[:, 0], (3 + env.junction_signal).float() / 10)
    with pytest.raises(ValueError, match="corridor"):
        make_env(matching=True, images={n: v for n, v in images.items() if n != "corridor"})


def test_reservoir_draws_a_fresh_image_of_the_class_at_every_visit():
    """§5.3.2: K images per observation; every visit (even a wall bump that stays put) draws anew."""
    names = ("start_0", "start_1", "corridor", "junction_0", "junction_1", "goal_left", "goal_right")
    K = 5
    # image k of observation n carries n in pixel 0 and k in pixel 1
    images = {n: torch.stack([torch.tensor([float(i), float(k), 0.0]) for k in range(K)]) for i, n in enumerate(names)}
    env = make_env(R=400, matching=True, images=images)
    assert env.reservoir_size == K and env.observation_table.shape == (len(names) * K, 3)
    first = env.reset()
    assert torch.equal(first[:, 0], env.initial_signal.float())  # start_0 / start_1
    assert torch.equal(env.obs_id // K, env.observation_class)
    bumped, _, _, _ = act(env, S)  # wall bump at the start: same observation class, new draw
    assert torch.equal(bumped[:, 0], first[:, 0])
    assert (bumped[:, 1] != first[:, 1]).float().mean() > 0.7  # P(same draw) = 1/K
    assert set(bumped[:, 1].long().tolist()) == set(range(K))
    with pytest.raises(ValueError, match="same size"):
        make_env(matching=True, images={**images, "corridor": images["corridor"][:2]})


def test_digit_reservoir_images_come_from_their_class():
    from ferl.envs.digit_tmaze import DigitTMaze
    from test_digit_floor import tiny_split

    data = tiny_split()
    classes = {
        "start_0": 0,
        "start_1": 1,
        "corridor": 2,
        "junction_0": 0,
        "junction_1": 1,
        "goal_left": 3,
        "goal_right": 4,
    }
    env = DigitTMaze(
        3,
        torch.Generator().manual_seed(0),
        data,
        classes,
        reservoir_size=4,
        binarize_threshold=None,
        corridor_length=3,
        max_steps=10,
        matching=True,
    )
    pools = {c: data.train_images[data.train_labels == c][:4] for c in range(5)}
    for name, label in classes.items():
        n = env.observation_names.index(name)
        assert torch.equal(env.observation_table[n * 4 : (n + 1) * 4], pools[label])
    with pytest.raises(ValueError, match=r"env.reservoir_size"):
        DigitTMaze(1, torch.Generator(), data, classes, reservoir_size=10_000, matching=True)
