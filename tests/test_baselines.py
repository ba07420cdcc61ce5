"""The baseline actors (``actor=mlp_q|oracle|drqn``) checked against independent computations:
the MLP-Q update against autograd, the oracle's tabular values against value iteration on the
maze's definition, DRQN's GRU and its BPTT gradient against torch.nn.GRU run run by run, its Adam
against torch.optim.Adam."""

import numpy as np
import pytest
import torch

from ferl.actors.mlp_q import MLPQActor
from ferl.actors.recurrent_q import RecurrentQActor
from ferl.actors.tabular import TabularQActor
from ferl.actors.td import first_action, td_step
from ferl.envs.tmaze import TMaze, maze_tables
from ferl.interfaces import EndedEpisode
from ferl.schedules import Constant

R, S, NA, H = 3, 5, 4, 6
SIZES = dict(n_runs=R, n_state=S, n_actions=NA, n_hidden=H)  # the actors' sizes, by keyword


def schedules(lr=0.1, beta=1.0):
    return dict(lr=Constant(lr), beta=Constant(beta))


def test_mlp_q_update_is_alpha_delta_times_the_autograd_gradient_of_q():
    actor = MLPQActor(
        **SIZES, td_rule="sarsa", gamma=0.9, lr_norm="none", init_std=0.5, td_fresh=False, seed=3, **schedules()
    )
    actor.b_1.normal_(generator=torch.Generator().manual_seed(1))
    gen = torch.Generator().manual_seed(0)
    s = torch.rand(R, 1, S, generator=gen)
    a = torch.randint(NA, (R, 1), generator=gen)
    delta = torch.randn(R, 1, generator=gen)
    names = ("W_1", "b_1", "W_2", "b_2")
    before = {n: getattr(actor, n).clone().requires_grad_() for n in names}
    # Q(s, a) written out independently of the actor's evaluate
    h = torch.sigmoid(torch.einsum("rbs,rsh->rbh", s, before["W_1"]) + before["b_1"][:, None])
    q = torch.einsum("rbh,rha->rba", h, before["W_2"]) + before["b_2"][:, None]
    q_sa = q.gather(-1, a.unsqueeze(-1)).sum()
    grads = dict(zip(names, torch.autograd.grad(q_sa, [before[n] for n in names])))
    F, cache = actor.evaluate(s)
    torch.testing.assert_close(-F, q.detach())
    lr = 0.3
    actor.learn(s, a, cache[:, :, 0], delta, lr, s, a, None, None)
    for n in names:
        step = lr * delta.view(R, *[1] * (grads[n].dim() - 1)) * grads[n]
        torch.testing.assert_close(getattr(actor, n), before[n].detach() + step, rtol=1e-5, atol=1e-6)


def value_iteration_q(corridor_length: int, gamma: float, rewards=(5.0, -1.0, -0.1)) -> np.ndarray:
    """Q* (P, 4, side) of the infinite-horizon maze (the cut-off is not terminal, §4.3.1)."""
    nxt, reward = maze_tables(corridor_length, *rewards)
    terminal = nxt >= corridor_length
    Q = np.zeros(reward.shape)
    for _ in range(2000):
        V = Q.max(1)  # (P, side)
        Q = reward + gamma * np.where(terminal[..., None], 0.0, V[nxt])
    return Q


def test_oracle_tabular_values_are_the_value_iteration_fixed_point():
    """Q-learning with α = 1 on a deterministic maze, acting uniformly at random (β = 0): every
    table entry of a non-goal true state converges to Q* of value iteration."""
    T_min, gamma, runs = 3, 0.95, 2
    gen = torch.Generator().manual_seed(0)
    env = TMaze(runs, gen, corridor_length=T_min, max_steps=10, true_state=True)
    actor = TabularQActor(
        n_runs=runs,
        n_state=env.observation_size,
        n_actions=env.n_actions,
        td_rule="q",
        gamma=gamma,
        **schedules(lr=1.0, beta=0.0),
    )
    alive = torch.ones(runs, 1, dtype=torch.bool)
    for _ in range(1500):
        env.reset()
        s = env.observe().unsqueeze(1)
        a, F_sa, c_sa = first_action(actor, s, 0.0, gen)
        while not bool(env.done.all()):
            active = ~env.done
            r, terminated, _ = env.advance(a.squeeze(1))
            s_next = env.observe().unsqueeze(1)
            a, F_sa, c_sa, _ = td_step(
                actor,
                s,
                a,
                F_sa,
                c_sa,
                r,
                s_next,
                1.0,
                0.0,
                gen,
                None,
                alive,
                (terminated | ~active).unsqueeze(1),
                active.unsqueeze(1),
            )
            s = s_next
    Q_star = value_iteration_q(T_min, gamma)
    for position in range(T_min):
        for s0 in (0, 1):
            state = position * 4 + 2 * s0  # regular maze: s1 = 0 (ferl.envs.tmaze.true_state_names)
            side = s0  # s0 = 1 rewards the right goal
            np.testing.assert_allclose(
                actor.Q[:, state].numpy(), np.broadcast_to(Q_star[position, :, side], (runs, 4)), atol=1e-4
            )


def test_true_state_view_names_every_state_once_and_keeps_the_dynamics():
    gen_a, gen_b = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    seen, oracle = TMaze(4, gen_a, matching=True), TMaze(4, gen_b, matching=True, true_state=True)
    actions = torch.Generator().manual_seed(1)
    for _ in range(30):
        a = torch.randint(4, (4,), generator=actions)
        r_seen, term_seen, _ = seen.advance(a)
        r_oracle, term_oracle, _ = oracle.advance(a)
        assert torch.equal(r_seen, r_oracle) and torch.equal(term_seen, term_oracle)
        expected = oracle.position * 4 + 2 * oracle.initial_signal + oracle.junction_signal
        assert torch.equal(oracle.observe().argmax(1), expected)
        assert torch.equal(oracle.observe().sum(1), torch.ones(4))
        if bool(seen.done.all()):
            seen.reset(), oracle.reset()
    assert len(set(oracle.observation_names)) == oracle.observation_size == (3 + 2) * 4


def reference_gru(actor: RecurrentQActor, r: int) -> torch.nn.GRUCell:
    """torch.nn.GRUCell holding run r's weights."""
    cell = torch.nn.GRUCell(actor.W_x.shape[1], actor.n_hidden)
    with torch.no_grad():
        cell.weight_ih.copy_(actor.W_x[r].T)
        cell.weight_hh.copy_(actor.W_h[r].T)
        cell.bias_ih.copy_(actor.b_x[r])
        cell.bias_hh.copy_(actor.b_h[r])
    return cell


def test_gru_step_is_torch_grucell_run_by_run():
    actor = RecurrentQActor(**SIZES, gamma=0.9, seed=2, **schedules())
    x = torch.randn(R, 7, S + NA)
    h = torch.randn(R, 7, H)
    out = actor.core.step(actor.params(), x, h)
    for r in range(R):
        torch.testing.assert_close(out[r], reference_gru(actor, r)(x[r], h[r]))


def episodes_batch(T=6, B=5, seed=0) -> dict:
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.randint(1, T + 1, (R, B), generator=gen)
    return {
        "states": torch.rand(R, B, T + 1, S, generator=gen),
        "actions": torch.randint(NA, (R, B, T), generator=gen),
        "rewards": torch.randn(R, B, T, generator=gen),
        "lengths": lengths,
        "terminated": torch.rand(R, B, generator=gen) < 0.5,
    }


def reference_loss(actor: RecurrentQActor, r: int, batch: dict, cell, W_q, b_q) -> torch.Tensor:
    """Run r's DRQN loss step by step in Python, with torch.nn.GRUCell and the target network."""
    target_cell = torch.nn.GRUCell(cell.input_size, cell.hidden_size)
    with torch.no_grad():
        target_cell.weight_ih.copy_(actor.W_x_target[r].T)
        target_cell.weight_hh.copy_(actor.W_h_target[r].T)
        target_cell.bias_ih.copy_(actor.b_x_target[r])
        target_cell.bias_hh.copy_(actor.b_h_target[r])
    losses = []
    for b in range(batch["states"].shape[1]):
        h = torch.zeros(actor.n_hidden)
        h_target = torch.zeros(actor.n_hidden)
        prev = torch.zeros(NA)
        qs, q_targets = [], []
        for t in range(batch["states"].shape[2]):
            x = torch.cat([batch["states"][r, b, t], prev])
            h = cell(x, h)
            with torch.no_grad():
                h_target = target_cell(x, h_target)
                q_targets.append(h_target @ actor.W_q_target[r] + actor.b_q_target[r])
            qs.append(h @ W_q + b_q)
            if t < batch["actions"].shape[2]:
                prev = torch.nn.functional.one_hot(batch["actions"][r, b, t], NA).float()
        n = int(batch["lengths"][r, b])
        errors = []
        for t in range(n):
            terminal = t == n - 1 and bool(batch["terminated"][r, b])
            y = batch["rewards"][r, b, t] + (0.0 if terminal else actor.gamma * q_targets[t + 1].max())
            errors.append(torch.nn.functional.huber_loss(qs[t][batch["actions"][r, b, t]], y))
        losses.append(torch.stack(errors))
    return torch.cat(losses).mean()


def test_drqn_bptt_gradient_of_every_run_equals_a_per_run_reference():
    """The batched loss's gradient with respect to run r's parameters is run r's own loss gradient,
    computed by an independent per-episode Python unroll with torch.nn.GRUCell."""
    actor = RecurrentQActor(**SIZES, gamma=0.9, seed=4, **schedules())
    for name in actor.names:  # a target network that differs from the online one
        getattr(actor, f"{name}_target").add_(torch.randn_like(getattr(actor, name)) * 0.1)
    batch = episodes_batch()
    p = {name: value.clone().requires_grad_() for name, value in actor.params().items()}
    grads = dict(zip(p, torch.autograd.grad(actor.loss(p, batch), list(p.values()))))
    for r in range(R):
        cell = reference_gru(actor, r)
        W_q, b_q = actor.W_q[r].clone().requires_grad_(), actor.b_q[r].clone().requires_grad_()
        loss = reference_loss(actor, r, batch, cell, W_q, b_q)
        ref = torch.autograd.grad(loss, [cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh, W_q, b_q])
        for name, expected in zip(actor.names, (ref[0].T, ref[1].T, ref[2], ref[3], ref[4], ref[5])):
            torch.testing.assert_close(grads[name][r], expected, rtol=1e-4, atol=1e-6)


def test_drqn_adam_step_equals_torch_adam():
    actor = RecurrentQActor(**SIZES, gamma=0.9, seed=1, **schedules())
    batch = episodes_batch(seed=3)
    params = {name: value.clone().requires_grad_() for name, value in actor.params().items()}
    optimiser = torch.optim.Adam(list(params.values()), lr=0.01)
    for _ in range(3):
        optimiser.zero_grad()
        actor.loss(params, batch).backward()
        optimiser.step()
        actor.adam_step(batch, 0.01)
    for name in actor.names:
        torch.testing.assert_close(getattr(actor, name), params[name].detach(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("draws", [3])
def test_drqn_replay_draws_per_run_and_resumes_from_its_extra_state(draws):
    actor = RecurrentQActor(**SIZES, gamma=0.9, batch_episodes=4, updates_per_episode=0, seed=0, **schedules())
    T = 4
    for k in range(draws):
        actor.end_episode(
            EndedEpisode(
                torch.full((T, R, S), float(k)),
                torch.full((R, 1, S), float(k)),
                torch.zeros(T, R, dtype=torch.long),
                torch.zeros(T, R),
                torch.full((R,), T),
                torch.ones(R, dtype=torch.bool),
                T,
            ),
            0.01,
        )
    copy = RecurrentQActor(**SIZES, gamma=0.9, batch_episodes=4, updates_per_episode=0, seed=0, **schedules())
    copy.load_state_dict(actor.state_dict())
    first, again = actor.sample(), copy.sample()
    assert torch.equal(first["states"], again["states"])
    assert set(first["states"][:, :, 0, 0].flatten().tolist()) <= set(range(draws))


def test_drqn_forgets_its_memory_when_the_episode_ends():
    """``end_episode`` is where DRQN learns (nothing per step: ``learn`` leaves every weight) and
    where its memory starts afresh: the next episode's first Q is the untrained h = 0 one."""
    actor = RecurrentQActor(**SIZES, gamma=0.9, updates_per_episode=0, seed=2, **schedules())
    s = torch.rand(R, 1, S, generator=torch.Generator().manual_seed(4))
    F_fresh, _ = actor.evaluate(s)
    weights = {k: v.clone() for k, v in actor.named_buffers() if k not in ("h", "a_prev")}
    a, F_a, h, _ = actor.act(s, 1.0, torch.Generator().manual_seed(5))
    assert actor.learn(s, a, h, torch.ones(R, 1), 0.1, s, a, F_a, h) == (F_a, h)
    assert all(torch.equal(actor.get_buffer(k), v) for k, v in weights.items())
    assert not torch.equal(actor.evaluate(s)[0], F_fresh)  # h and a_{t-1} moved on with the act
    T = 3
    actor.end_episode(
        EndedEpisode(
            torch.zeros(T, R, S),
            torch.zeros(R, 1, S),
            torch.zeros(T, R, dtype=torch.long),
            torch.zeros(T, R),
            torch.full((R,), T),
            torch.ones(R, dtype=torch.bool),
            T,
        ),
        0.01,
    )
    assert (actor.h == 0).all() and (actor.a_prev == 0).all()
    assert torch.equal(actor.evaluate(s)[0], F_fresh)


def test_an_ended_episode_is_laid_out_per_run_and_padded_to_t_max():
    """``EndedEpisode.padded`` against the layout written out entry by entry: run r's states at
    its steps, then the last state, then zeros; actions and rewards run-major, zero after the
    lockstep episode's steps."""
    steps, T_max = 3, 5
    g = torch.Generator().manual_seed(6)
    states, last = torch.rand(steps, R, S, generator=g), torch.rand(R, 1, S, generator=g)
    actions, rewards = torch.randint(NA, (steps, R), generator=g), torch.rand(steps, R, generator=g)
    lengths, terminated = torch.tensor([3, 1, 2]), torch.tensor([True, False, True])
    s, a, r, n, term = EndedEpisode(states, last, actions, rewards, lengths, terminated, T_max).padded()
    assert s.shape == (R, T_max + 1, S) and a.shape == r.shape == (R, T_max)
    for run in range(R):
        for t in range(T_max + 1):
            want = states[t, run] if t < steps else last[run, 0] if t == steps else torch.zeros(S)
            assert torch.equal(s[run, t], want)
        for t in range(T_max):
            assert a[run, t] == (actions[t, run] if t < steps else 0)
            assert r[run, t] == (rewards[t, run] if t < steps else 0.0)
    assert torch.equal(n, lengths) and n is not lengths and torch.equal(term, terminated)


def test_the_continuing_td_phase_refuses_an_actor_that_learns_only_from_episodes():
    """A continuing task has no episode ends, so ``end_episode`` would never come: refused in one
    line before anything runs (``Actor.learns_from_episodes``)."""
    from types import SimpleNamespace

    from ferl.config.params import ConfigError
    from ferl.trainers.continuing_td import ContinuingTD
    from ferl.trainers.phased import RunControl

    job = SimpleNamespace(
        actor=RecurrentQActor(**SIZES, gamma=0.9, **schedules()),
        env=SimpleNamespace(task="floor"),
        R=R,
        control=RunControl(log_every=5, checkpoint_every=5, checkpoint_minutes=0.0, divergence_limit=1e6),
    )
    with pytest.raises(ConfigError, match=r"^actor=drqn learns from whole episodes, and the continuing task floor"):
        ContinuingTD(10, 1, 0).prepare(job)


def test_an_actor_without_the_logging_views_records_no_hidden_activations():
    """``ActorViews`` is optional: the probe records of an actor without ``hidden`` keep the rest."""
    from types import SimpleNamespace

    from ferl.interfaces import ActorViews
    from ferl.trainers.actor_logs import probe_visits

    class Viewless:  # an actor as far as the probe records are concerned, without the views
        pass

    steps = 4
    probes = torch.zeros(steps, R, dtype=torch.bool)
    probes[1, 0] = probes[2, 2] = True
    ep = {
        "probes": probes,
        "memories": [torch.rand(steps, R, 3)],
        "obs": torch.randint(5, (steps + 1, R)),
        "caches": torch.rand(steps, R, H),
    }
    env = SimpleNamespace(labels=lambda: {"cue": torch.tensor([1, 0, 1])})
    seen = {}
    for actor in (Viewless(), RecurrentQActor(**SIZES, gamma=0.9, **schedules())):
        seen[isinstance(actor, ActorViews)] = probe_visits(
            SimpleNamespace(actor=actor, env=env, predictors={"m": None}), 7, ep
        )
    assert set(seen[True]) - set(seen[False]) == {"hidden"}
    assert seen[False]["run"].tolist() == [0, 2] and seen[False]["step"].tolist() == [1, 2]
    assert torch.equal(seen[False]["observation"], ep["obs"][[1, 2], [0, 2]])
    assert torch.equal(seen[True]["hidden"], ep["caches"][[1, 2], [0, 2]].half())
