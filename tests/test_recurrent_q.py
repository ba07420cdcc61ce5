"""The recurrent Q-learner (ferl/actors/recurrent_q.py, docs/beyond.md) against independent
computations: every head's Q against NumPy (the free energy also against the brute-force sum over
the RBM's hidden configurations), every core's step against torch.nn's cells or its formula,
padding after an episode's end against the unpadded per-episode loss and gradient (autograd
through head and core), and ``actor=drqn`` against the DRQN module it replaced, run side by side."""

import math
import subprocess
import types
from itertools import product

import numpy as np
import pytest
import torch

from conftest import ROOT, validated_config
from ferl.actors.recurrent_q import RecurrentQActor
from ferl.interfaces import EndedEpisode
from ferl.schedules import Constant

R, S, NA, H, K = 3, 5, 4, 6, 4
SIZES = dict(n_runs=R, n_state=S, n_actions=NA, n_hidden=H)  # the actors' sizes, by keyword
HEADS = ("linear", "free_energy", "scaled_free_energy", "expected_energy")
MEMORIES = ("gru", "lstm", "elman", "esn")
DRQN_COMMIT = "83efea8"  # the last commit with ferl/actors/drqn.py, DRQN's own module


def actor(head="linear", memory="gru", **kwargs) -> RecurrentQActor:
    return RecurrentQActor(
        **SIZES, gamma=0.9, lr=Constant(0.01), beta=Constant(2.0), head=head, memory=memory, head_hidden=K, **kwargs
    )


def sigmoid(x):
    return 1 / (1 + np.exp(-x))


def numpy_q(head: str, p: dict, h: np.ndarray) -> np.ndarray:
    """Q (B, nA) of one run's h (B, H) by the formulas of ferl/actors/q_heads.py, action by action."""
    if head == "linear":
        return h @ p["W_q"] + p["b_q"]
    q = np.empty((h.shape[0], NA))
    for a in range(NA):
        x = h @ p["W_sh"] + p["W_ah"][a] + p["b_k"]
        visible = h @ p["b_s"] + p["b_a"][a]
        if head == "expected_energy":
            q[:, a] = visible + (x * sigmoid(x)).sum(-1)
        else:
            q[:, a] = (visible + np.log1p(np.exp(x)).sum(-1)) / (math.sqrt(H) if head == "scaled_free_energy" else 1)
    return q


@pytest.mark.parametrize("head", HEADS)
def test_every_heads_q_equals_numpy(head):
    agent = actor(head, seed=1)
    h = torch.randn(R, 7, H, dtype=torch.float64)
    p = {k: v.double() for k, v in agent.params().items()}
    q = agent.head.q(p, h)
    for r in range(R):
        np.testing.assert_allclose(q[r], numpy_q(head, {k: v[r].numpy() for k, v in p.items()}, h[r].numpy()), 1e-10)


def test_free_energy_head_is_the_log_sum_over_the_rbms_hidden_configurations():
    """−F(v) = log Σ_h exp(−E(v, h)), E = −vᵀW h − vᵀb_v − hᵀb_h (Eqs. 2.18, 2.20), by brute force
    over the 2^K hidden states, with v = (h_t, onehot(a))."""
    agent = actor("free_energy", seed=3)
    p = {k: v[0].double() for k, v in agent.params().items()}
    h = torch.randn(2, H, dtype=torch.float64)
    q = agent.head.q({k: v.unsqueeze(0) for k, v in p.items()}, h.unsqueeze(0))[0]
    W, b_v = torch.cat([p["W_sh"], p["W_ah"]]), torch.cat([p["b_s"], p["b_a"]])
    configs = torch.tensor(list(product((0.0, 1.0), repeat=K)), dtype=torch.float64)
    for b, a in product(range(2), range(NA)):
        v = torch.cat([h[b], torch.eye(NA, dtype=torch.float64)[a]])
        minus_energy = configs @ (W.T @ v) + v @ b_v + configs @ p["b_k"]
        torch.testing.assert_close(q[b, a], torch.logsumexp(minus_energy, 0))


def reference_step(memory: str, agent: RecurrentQActor, r: int, x: torch.Tensor, state: torch.Tensor):
    """Run r's core step on x (B, X) from state (B, ·) by torch.nn's cells or the formula."""
    p = {k: v[r] for k, v in agent.params().items()}
    if memory in ("gru", "lstm"):
        cell = (torch.nn.GRUCell if memory == "gru" else torch.nn.LSTMCell)(S + NA, H)
        with torch.no_grad():
            cell.weight_ih.copy_(p["W_x"].T)
            cell.weight_hh.copy_(p["W_h"].T)
            cell.bias_ih.copy_(p["b_x"])
            cell.bias_hh.copy_(p["b_h"] if memory == "gru" else torch.zeros_like(p["b_x"]))
            if memory == "gru":
                return cell(x, state)
            return torch.cat(cell(x, state.chunk(2, -1)), -1)
    if memory == "elman":  # Eq. 4.3, β_m = 1
        return torch.sigmoid(x @ p["W_x"] + state @ p["W_h"] + p["b_x"])
    return 0.5 * state + 0.5 * torch.tanh(x @ p["W_in"] + state @ p["W_res"].T)  # leak 0.5


@pytest.mark.parametrize("memory", MEMORIES)
def test_every_cores_step_equals_its_reference(memory):
    agent = actor(memory=memory, seed=2)
    x = torch.randn(R, 7, S + NA)
    state = torch.randn(R, 7, agent.core.state_size)
    out = agent.core.step(agent.params(), x, state)
    for r in range(R):
        with torch.no_grad():
            torch.testing.assert_close(out[r], reference_step(memory, agent, r, x[r], state[r]))


def test_esn_reservoir_has_the_spectral_radius_and_stays_fixed():
    agent = RecurrentQActor(
        n_runs=R,
        n_state=S,
        n_actions=NA,
        n_hidden=30,
        gamma=0.9,
        lr=Constant(0.01),
        beta=Constant(2.0),
        memory="esn",
        seed=2,
    )  # not nilpotent
    radius = torch.linalg.eigvals(agent.W_res.double()).abs().amax(-1)
    torch.testing.assert_close(radius, torch.full((R,), 0.95, dtype=torch.float64))
    assert "W_res" not in agent.names and "W_in" not in agent.names  # no Adam step moves them


def padded_batch(T=6, B=4, seed=0) -> dict:
    """Episodes of lengths 1 … T per run and episode, with large random values after their end."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "states": torch.rand(R, B, T + 1, S, generator=gen),
        "actions": torch.randint(NA, (R, B, T), generator=gen),
        "rewards": torch.randn(R, B, T, generator=gen),
        "lengths": torch.randint(1, T + 1, (R, B), generator=gen),
        "terminated": torch.rand(R, B, generator=gen) < 0.5,
    }


def episode(batch: dict, r: int, b: int) -> dict:
    """Run r's episode b cut at its length: one run, one episode, no padding."""
    n = int(batch["lengths"][r, b])
    cut = {"states": n + 1, "actions": n, "rewards": n}
    return {k: v[r : r + 1, b : b + 1, : cut[k]] if k in cut else v[r : r + 1, b : b + 1] for k, v in batch.items()}


@pytest.mark.parametrize("head,memory", [(h, "gru") for h in HEADS] + [("free_energy", m) for m in MEMORIES[1:]])
def test_padding_changes_neither_the_loss_nor_its_gradient_through_head_and_core(head, memory):
    """The batched loss and its autograd gradient (through head and core) equal those of each run's
    episodes unrolled one by one, unpadded: Σ_r Σ_b n_b L_rb / Σ_b n_b, L_rb an episode's mean."""
    agent = actor(head, memory, seed=4)
    for name in agent.names:  # a target network that differs from the online one
        getattr(agent, f"{name}_target").add_(torch.randn_like(getattr(agent, name)) * 0.1)
    batch = padded_batch()
    p = {k: v.clone().requires_grad_(k in agent.names) for k, v in agent.params().items()}
    trained = [p[k] for k in agent.names]
    loss = agent.loss(p, batch)
    grads = torch.autograd.grad(loss, trained)
    reference = 0.0
    for r in range(R):
        one = agent.slice_runs(slice(r, r + 1))
        p_r = {k: v[r : r + 1] for k, v in p.items()}
        n = batch["lengths"][r]
        reference = reference + sum(one.loss(p_r, episode(batch, r, b)) * n[b] for b in range(n.shape[0])) / n.sum()
    torch.testing.assert_close(loss, reference)
    for got, expected in zip(grads, torch.autograd.grad(reference, trained)):
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-6)


def ended(k: int, T: int = 4) -> EndedEpisode:
    """A synthetic episode of T steps in every run, different for each k."""
    gen = torch.Generator().manual_seed(k)
    return EndedEpisode(
        torch.rand(T, R, S, generator=gen),
        torch.rand(R, 1, S, generator=gen),
        torch.randint(NA, (T, R), generator=gen),
        torch.randn(T, R, generator=gen),
        torch.full((R,), T),
        torch.ones(R, dtype=torch.bool),
        T,
    )


def old_module(path: str, name: str, replace: str = "", **names) -> types.ModuleType:
    """``path`` as it was at DRQN_COMMIT (git), run as module ``name`` with ``names`` defined first
    and the line ``replace`` taken out."""
    source = subprocess.run(["git", "-C", str(ROOT), "show", f"{DRQN_COMMIT}:{path}"], capture_output=True, text=True)
    if source.returncode != 0:
        pytest.skip(f"no git history with {DRQN_COMMIT}")
    module = types.ModuleType(name)
    module.__dict__.update(names)
    exec(compile(source.stdout.replace(replace, ""), f"{name}.py", "exec"), module.__dict__)
    return module


def drqn_module() -> types.ModuleType:
    """ferl/actors/drqn.py as it was before the recurrent Q-learner replaced it, on the softmax
    actor base of the same commit (git)."""
    softmax = old_module("ferl/actors/softmax.py", "old_softmax")
    return old_module(
        "ferl/actors/drqn.py",
        "old_drqn",
        "from ferl.actors.softmax import SoftmaxActor, TDRule\n",
        SoftmaxActor=softmax.SoftmaxActor,
        TDRule=softmax.TDRule,
    )


def test_drqn_is_the_recurrent_q_learner_with_a_gru_and_a_linear_head():
    """Side by side with the old DRQNActor over episodes that act, replay and copy the target
    network: the same actions, the same parameters, bit for bit."""
    cfg = validated_config(["experiment=popgym_repeat_previous_easy", "actor=drqn", "predictor=none"])
    assert cfg.actor._target_.endswith("RecurrentQActor") and (cfg.actor.head, cfg.actor.memory) == ("linear", "gru")
    kwargs = {"batch_episodes": 3, "target_every": 2, "seed": 5}
    old = drqn_module().DRQNActor(R, S, NA, H, 0.9, Constant(0.05), Constant(2.0), **kwargs)
    new = RecurrentQActor(
        **SIZES, gamma=0.9, lr=Constant(0.05), beta=Constant(2.0), head="linear", memory="gru", **kwargs
    )
    for k in range(5):
        s = torch.rand(R, 1, S, generator=torch.Generator().manual_seed(100 + k))
        a_old = old.act(s, 2.0, torch.Generator().manual_seed(k))
        a_new = new.act(s, 2.0, torch.Generator().manual_seed(k))
        assert all(torch.equal(x, y) for x, y in zip(a_old, a_new))
        old.end_episode(ended(k), 0.05)
        new.end_episode(ended(k), 0.05)
    for name in ("W_x", "W_h", "b_x", "b_h", "W_q", "b_q"):
        for suffix in ("", "_m", "_v", "_target"):
            assert torch.equal(getattr(old, name + suffix), getattr(new, name + suffix)), name + suffix
    assert old.describe().items() <= new.describe().items()  # and the head: linear


def cue_episode(agent: RecurrentQActor, cues: torch.Tensor, beta: float, gen: torch.Generator, delay: int = 2):
    """A cue (R,) shown at t = 0 as a one-hot among S = 3 nodes, then ``delay`` blank steps; the
    last action earns 1 if it names the cue. Returns the ended episode and the last actions."""
    blank = torch.tensor([0.0, 0.0, 1.0]).expand(R, 1, 3)
    states, actions = [], []
    for t in range(delay + 1):
        s = (
            torch.nn.functional.pad(torch.nn.functional.one_hot(cues, 3).float()[:, None, :2], (0, 1))
            if t == 0
            else blank
        )
        a = agent.act(s, beta, gen)[0]
        states.append(s[:, 0])
        actions.append(a[:, 0])
    T = delay + 1
    rewards = torch.zeros(T, R)
    rewards[-1] = (actions[-1] == cues).float()
    ended = EndedEpisode(
        torch.stack(states),
        blank.clone(),
        torch.stack(actions),
        rewards,
        torch.full((R,), T),
        torch.ones(R, dtype=torch.bool),
        T,
    )
    return ended, actions[-1]


def test_the_free_energy_head_learns_to_remember_a_cue_through_its_core():
    """A reduced-scale memory task (a T-maze with the corridor cut to 2 blank steps): a memoryless
    agent names the cue half the time; trained end to end, every run names it in ≥ 95 % of
    greedy episodes."""
    agent = RecurrentQActor(
        n_runs=R,
        n_state=3,
        n_actions=2,
        n_hidden=8,
        gamma=0.9,
        lr=Constant(0.01),
        beta=Constant(3.0),
        head="free_energy",
        head_hidden=8,
        target_every=20,
        seed=0,
    )
    gen = torch.Generator().manual_seed(0)
    for _ in range(400):
        ended, _ = cue_episode(agent, torch.randint(2, (R,), generator=gen), 3.0, gen)
        agent.end_episode(ended, 0.01)
    agent.updates_per_episode = 0
    correct = torch.zeros(R)
    for _ in range(100):
        cues = torch.randint(2, (R,), generator=gen)
        ended, last = cue_episode(agent, cues, 50.0, gen)  # near greedy
        agent.end_episode(ended, 0.0)
        correct += (last == cues).float()
    assert (correct >= 95).all(), correct


@pytest.mark.parametrize("episodes", [3, 11])
def test_a_checkpoint_keeps_only_the_replays_filled_slots_and_restores_it_whole(episodes):
    """The checkpoint's replay holds the min(stored, K) slots that hold episodes, in storages of
    their own size (not views of the whole replay); restored, the replay equals the one saved,
    and the restored actor replays the same episodes and learns the same steps."""
    K = 8
    saved_actor, restored = actor(replay_episodes=K, seed=3), actor(replay_episodes=K, seed=3)
    for k in range(episodes):
        saved_actor.end_episode(ended(k), 0.01)
    state = saved_actor.get_extra_state()
    for key, value in state["replay"].items():
        assert value.shape[1] == min(episodes, K), key
        assert value.untyped_storage().nbytes() == value.numel() * value.element_size(), key
    restored.load_state_dict(saved_actor.state_dict())
    for key, value in saved_actor.replay.items():
        assert torch.equal(restored.replay[key], value), key
    for agent in (saved_actor, restored):
        agent.end_episode(ended(100), 0.01)
    for name in saved_actor.names:
        assert torch.equal(getattr(restored, name), getattr(saved_actor, name)), name
