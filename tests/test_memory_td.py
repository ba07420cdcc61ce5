"""TD into the predictors' memory (``trainer.td_to_memory``, ferl/trainers/memory_td.py): the actor's
∂Q/∂s of every value form against autograd through a brute-force sum over hidden states; the λ step's
change of every memory parameter against autograd of −λ Σ_t δ_t Q(s_t(θ), a_t) through the actor's
own F and the unrolled memories, and against central finite differences, on padded episodes (NaN
in the padding) of two predictors at once; λ = 0 equal to a run without the key; the same seed
giving the same run with λ > 0."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import open_dict

from conftest import compose_config, train_job
from ferl.predictors import elman
from ferl.predictors.recurrent import predictor
from ferl.trainers.memory_td import td_to_memory
from test_tmaze_resume import records
from test_value_forms import FORMS, brute_force_q, make_actor

Y, A = 3, 4  # observation bits, actions


@pytest.mark.parametrize("code", ["onehot", "binary"])
@pytest.mark.parametrize("q", FORMS)
def test_state_gradient_of_every_value_form_against_autograd(q, code):
    """∂Q(s, a)/∂s, written out, against autograd of Q summed over all 2^H hidden states."""
    actor = make_actor(q, code=code)
    R, B, S = 2, 3, 3
    s = torch.rand(R, B, S, dtype=torch.float64)
    a = torch.randint(0, 4, (R, B))
    got = actor.state_gradient(s, a)
    params = {name: getattr(actor, name) for name in ("W_sh", "W_ah", "b_s", "b_a", "b_h")}
    for r in range(R):
        run = {k: v[r] for k, v in params.items()}
        for b in range(B):
            x = s[r, b].clone().requires_grad_()
            (want,) = torch.autograd.grad(brute_force_q(q, run, x, actor.code(a[r : r + 1, b : b + 1])[0, 0], S), x)
            torch.testing.assert_close(got[r, b], want)


def make_predictor(memory, n_memory, R, seed):
    kw = {"context": 8} if memory == "transformer" else {}
    return predictor(
        memory=memory, n_runs=R, n_obs=Y, n_actions=A, n_memory=n_memory, n_reward=2, init_std=0.7, seed=seed, **kw
    ).double()


def unrolled(p, params, y, a):
    """m_0 … m_T under ``params`` (autograd leaves): the Elman memory's module function, else unroll_with."""
    return elman.unroll(params, p.gains, y, a) if p.kind == "elman" else p.unroll_with(params, y, a)


def episode(R=3, n=6, seed=0):
    """Padded episodes of R runs, lengths n, n − 2, 1 …: y (R, 1, n+1, Y), a (R, 1, n, A) with NaN
    after each run's end, lengths (R, 1), actions (n, R), δ (n, R) 0 after the end, and the
    observation part of the actor's state (n, R, Y), large where the episode had ended."""
    g = torch.Generator().manual_seed(seed)
    lengths = torch.tensor([n, n - 2, 1][:R]).unsqueeze(1)
    steps = torch.arange(n + 1)
    y = torch.randint(0, 2, (R, 1, n + 1, Y), generator=g).double()
    actions = torch.randint(0, A, (n, R), generator=g)
    a = F.one_hot(actions.T.unsqueeze(1), A).double()
    valid = steps <= lengths.unsqueeze(-1)  # (R, 1, n+1)
    y = torch.where(valid.unsqueeze(-1), y, torch.nan)
    a = torch.where(valid[..., 1:].unsqueeze(-1), a, torch.nan)
    acted = valid[:, 0, 1:].T  # (n, R): t < T
    deltas = torch.where(acted, torch.randn(n, R, generator=g, dtype=torch.float64), 0.0)
    obs = torch.where(acted.unsqueeze(-1), torch.nan_to_num(y[:, 0, :n].transpose(0, 1)), 50.0)
    return y, a, lengths, actions, deltas, obs


def state_of(obs, memories):
    """The actor's state (n, R, S): the observation, then every predictor's m_0 … m_{n−1}."""
    return torch.cat([obs, *(m[:, 0, :-1].transpose(0, 1) for m in memories)], -1)


def loss(predictors, params, actor, y, a, actions, deltas, obs, lam):
    """−λ Σ_t δ_t Q(s_t, a_t) with the memories unrolled under ``params`` and Q = −F of the actor's
    own F (no ∂Q/∂s): the objective the step descends, computed independently of it."""
    memories = [unrolled(p, q, y, a) for p, q in zip(predictors, params)]
    F_sa, _ = actor.evaluate_actions(state_of(obs, memories).transpose(0, 1), actions.T)
    return -lam * (deltas.T * -F_sa).sum()


@pytest.mark.parametrize("second", ["gru", "lstm", "transformer"])
@pytest.mark.parametrize("q", FORMS)
def test_lambda_step_against_autograd_and_finite_differences_on_padded_episodes(q, second):
    R, lam = 3, 0.7
    predictors = [make_predictor("elman", 4, R, seed=1), make_predictor(second, 3, R, seed=2)]
    actor = make_actor(q, R=R, S=Y + 4 + 3, A=A, H=5)
    y, a, lengths, actions, deltas, obs = episode(R)
    valid = (torch.arange(y.shape[2]) <= lengths.unsqueeze(-1)).unsqueeze(-1)
    y0, a0 = torch.where(valid, y, 0.0), torch.where(valid[:, :, 1:], a, 0.0)  # the padding, zeroed here
    before = [[q.detach().clone() for q in p.memory_parameters()] for p in predictors]
    with torch.no_grad():
        states = state_of(obs, [p.unroll(y0, a0) for p in predictors])
    leaves = [[q.clone().requires_grad_() for q in qs] for qs in before]
    want = torch.autograd.grad(
        loss(predictors, leaves, actor, y0, a0, actions, deltas, obs, lam), [q for qs in leaves for q in qs]
    )
    td_to_memory(predictors, actor, y, a, lengths, states, actions, deltas, lam)
    got = [(b - q.detach()) / p.lr for p, qs in zip(predictors, before) for b, q in zip(qs, p.memory_parameters())]
    assert all(g.abs().sum() > 0 for g in got[:3])  # the step moved the Elman memory's weights
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w)
    # central finite differences of the loss on a few entries of every parameter
    gen, eps = torch.Generator().manual_seed(3), 1e-6
    flat = [q for qs in before for q in qs]
    for k, q in enumerate(flat):
        for i in torch.randint(0, q.numel(), (2,), generator=gen).tolist():
            shifted = []
            for sign in (1, -1):
                params = [x.clone() for x in flat]
                params[k].view(-1)[i] += sign * eps
                split = [params[:5], params[5:]]
                shifted.append(loss(predictors, split, actor, y0, a0, actions, deltas, obs, lam))
            assert float((shifted[0] - shifted[1]) / (2 * eps)) == pytest.approx(float(got[k].view(-1)[i]), abs=1e-6)


ONLINE = ["experiment=table4_1_matching", "trainer=online", "n_runs=2", "trainer.n_episodes=40", "trainer.log_every=20"]


def run(tmp_path, name, *overrides, drop_key=False):
    cfg = compose_config([*ONLINE, *overrides])
    if drop_key:  # the config as it was before the key existed
        with open_dict(cfg):
            del cfg.trainer["td_to_memory"], cfg.trainer.phases.online["td_to_memory"]
    summary = train_job(cfg, tmp_path / name)
    return summary["metrics"], {k: records(tmp_path / name, k) for k in ("episodes", "online")}


def assert_same(x, y):
    assert x[0] == y[0]
    for name in y[1]:
        for key in (k for k in y[1][name] if not k.endswith("_time_s")):  # the phase's clock
            np.testing.assert_array_equal(x[1][name][key], y[1][name][key], err_msg=f"{name}.{key}")


def test_lambda_zero_is_the_run_without_the_key_and_a_seed_repeats_with_lambda(tmp_path, monkeypatch):
    without = run(tmp_path, "without", drop_key=True)
    lam = run(tmp_path, "lam", "trainer.td_to_memory=0.5")
    again = run(tmp_path, "again", "trainer.td_to_memory=0.5")
    assert_same(again, lam)  # the same seed, the same run
    assert not np.array_equal(lam[1]["online"]["prediction_error"], without[1]["online"]["prediction_error"])
    import ferl.trainers.online_episodes as online

    def never(*args):
        raise AssertionError("λ = 0 takes no TD step into the memory")

    monkeypatch.setattr(online, "td_to_memory", never)
    assert_same(run(tmp_path, "zero", "trainer.td_to_memory=0"), without)
