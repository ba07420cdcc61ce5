"""baselines/large_action_bound.py, the supervised bound of the large-action task: on tiny tasks
whose 2^K actions can be enumerated, its rewards are the environment's, its PoE fit by regression
matches the exact rewards where the task is representable, its key-state construction is exact,
Gibbs selection of the fitted PoE earns what the brute-force best of its Q earns, and its local
search ends in local optima no worse than brute force finds among its starts."""

import importlib.util

import pytest
import torch

from conftest import ROOT
from ferl.actors.free_energy import FERLActor
from ferl.bits import to_bits
from ferl.envs.large_action import LargeActionTask
from ferl.schedules import Constant

spec = importlib.util.spec_from_file_location("large_action_bound", ROOT / "baselines" / "large_action_bound.py")
bound = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bound)

R, S, K = 2, 3, 4  # tiny: 16 actions
TD, INIT = {"td_rule": "sarsa", "gamma": 0.0}, {"init_std": 0.4, "seed": 0}


@pytest.fixture(autouse=True)
def one_thread():
    """Small tensors: one thread, or the fits' thousands of tiny steps wait on each other's threads."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny(states="key_states", n_hidden=4, key_states=2):
    task = LargeActionTask(
        R, torch.Generator().manual_seed(0), state_bits=S, action_bits=K, key_states=key_states, states=states, seed=5
    )
    schedules = {"lr": Constant(0.01), "beta": Constant(10.0)}
    gibbs = {"action_code": "binary", "action_selection": "gibbs", "gibbs_sweeps": 100}  # the experiment's
    actor = FERLActor(n_runs=R, n_state=S, n_actions=2**K, n_hidden=n_hidden, **schedules, **gibbs, **TD, **INIT)
    return task, actor


def all_pairs(task, states):
    """Every (state, action) pair of the given states (R, n, S): s (R, n·2^K, S), bits (R, n·2^K, K)."""
    n = states.shape[1]
    bits = to_bits(torch.arange(2**K), K).repeat(R, n, 1)
    return states.repeat_interleave(2**K, 1), bits


def test_rewards_are_the_environments_own():
    task, _ = tiny(states="uniform", key_states=3)
    g = torch.Generator().manual_seed(1)
    s = bound.states(task, 300)
    bits = bound.draw_actions(task, s, g)
    got = bound.rewards(task, s, bits)
    for b in range(300):  # the environment, one pair per run at a time
        want = task.reward(s[:, b], torch.tensor([int("".join(str(int(x)) for x in bits[r, b]), 2) for r in range(R)]))
        assert torch.equal(got[:, b], want)
    # the mixture covers both random actions and the key actions themselves
    assert got.min() < K / 2 and (got == K).float().mean() > 0.15


def test_the_key_state_construction_is_exact():
    task, actor = tiny(n_hidden=3)  # one unit more than the keys: switched off
    bound.construct(actor, task, gain=60.0, margin=0.0)
    s, bits = all_pairs(task, task.keys)
    r = bound.rewards(task, s, bits)
    assert r.min() == 0 and r.max() == K
    # Q = softplus(r) = r + ln(1 + e^−r): the reward itself up to e^−r
    assert (bound.q_values(actor, s, bits) - torch.nn.functional.softplus(r)).abs().max() < 1e-4


@pytest.mark.parametrize("states", ["key_states", "uniform"])
def test_the_fit_matches_exact_rewards_and_gibbs_reaches_the_best_of_its_q(states):
    """Two key states split the 8 states by one hyperplane (the Hamming distances differ by a linear
    function of s), and the reward is linear in a within each half: 2 hidden units represent it."""
    torch.manual_seed(0)
    task, actor = tiny(states)
    g = torch.Generator().manual_seed(2)
    bound.fit(actor, task, steps=1500, batch=64, lr=0.05, generator=g)
    every_state = to_bits(torch.arange(2**S), S).expand(R, -1, -1)
    space = task.keys if states == "key_states" else every_state
    s, bits = all_pairs(task, space)
    q, r = bound.q_values(actor, s, bits), bound.rewards(task, s, bits)
    assert (q - r).pow(2).mean().sqrt() < 0.25
    # the enumerated F of the actor (a second path through the same RBM) agrees with q_values
    F, _ = actor.evaluate(space)
    assert torch.allclose(-F.flatten(1), q, atol=1e-4)
    # brute force: the reward of each state's best action under the fitted Q
    best = q.view(R, -1, 2**K).argmax(-1)
    best_reward = r.view(R, -1, 2**K).gather(-1, best.unsqueeze(-1)).mean()
    assert best_reward == K  # the fit ranks the optimum first
    chosen = bound.gibbs_choices(actor, space.repeat(1, 50, 1), 10.0, g)
    assert bound.rewards(task, space.repeat(1, 50, 1), chosen).mean() > best_reward - 0.1


def test_local_search_ends_in_local_optima_at_least_as_good_as_its_starts():
    """Random weights (many local optima): every end has no improving single flip (brute force over
    its K neighbours by the enumerated F), its Q is ≥ its start's, and the best of the starts' ends
    is at least the brute-force best among those ends."""
    task, actor = tiny(states="uniform", n_hidden=6, key_states=3)
    for name in ("W_sh", "W_ah", "b_h", "b_a"):
        getattr(actor, name).normal_(0, 2.0, generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(4)
    s = bound.states(task, 20)
    starts = to_bits(torch.randint(2**K, (R, 20, 3), generator=g), K)
    ends = bound.ascend(actor, s.repeat_interleave(3, 1), starts.flatten(1, 2))
    F, _ = actor.evaluate(s)  # (R, 20, 16): −Q of every action
    q_all = -F.repeat_interleave(3, 1)
    index = (ends * 2 ** torch.arange(K - 1, -1, -1)).sum(-1).long()
    q_end = q_all.gather(-1, index.unsqueeze(-1)).squeeze(-1)
    start_index = (starts.flatten(1, 2) * 2 ** torch.arange(K - 1, -1, -1)).sum(-1).long()
    assert (q_end >= q_all.gather(-1, start_index.unsqueeze(-1)).squeeze(-1) - 1e-5).all()
    neighbours = index.unsqueeze(-1) ^ (1 << torch.arange(K))
    assert (q_all.gather(-1, neighbours) <= q_end.unsqueeze(-1) + 1e-5).all()
    found = bound.best_found(actor, task, s, starts)
    q_found = bound.q_values(actor, s, found)
    assert (q_found >= q_end.view(R, 20, 3).max(-1).values - 1e-5).all()
    assert (q_found <= -F.min(-1).values + 1e-5).all()  # never above the true maximum


def test_the_bound_uses_the_experiments_task_and_gibbs_settings():
    task, actor, beta = bound.experiment("large_action_key_states", 13, 2)
    same = LargeActionTask(2, torch.Generator().manual_seed(0), states="key_states", seed=300_000)
    assert torch.equal(task.keys, same.keys) and torch.equal(task.key_actions, same.key_actions)
    assert task.states == "key_states" and beta == pytest.approx(10.0)
    assert (actor.n_hidden, actor.gibbs_sweeps, actor.W_ah.shape[1]) == (13, 100, 40)


@pytest.mark.parametrize("argv", [["--runs", "0"], ["--states", "10", "--search-states", "20"], ["--lr", "0"]])
def test_bad_input_is_one_line_before_any_work(argv, capsys):
    with pytest.raises(SystemExit) as refused:
        bound.main(argv)
    assert str(refused.value).startswith("large_action_bound.py: ") and "\n" not in str(refused.value)
    assert capsys.readouterr().out == ""  # nothing measured or printed
