"""Elman predictor: Eqs. (4.1–4.5) against a per-run, per-step loop, BPTT gradients of Eqs. (4.6)
and (5.2) against finite differences, pattern-mode SGD (§4.3.1) batched vs single runs, learning
and run independence."""

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from ferl.predictors.elman import ElmanPredictor
from ferl.predictors.heads import clean
from ferl.predictors.training import PredictorBatch

Y, A, M, NR = 4, 3, 5, 2
GAINS = dict(c_y=0.7, c_a=1.3, beta_m=0.8, beta_y=1.2, beta_r=0.9, rho_y=1.5, rho_r=2.5)
KINDS = [
    dict(reward_output="bits"),
    dict(reward_output="linear"),
    dict(reward_output="none"),
    dict(reward_output="linear", predict_obs=False),
]


def make(R=2, seed=0, **kw):
    kw = {**GAINS, "init_std": 0.7, **kw}
    return ElmanPredictor(R, Y, A, n_memory=M, n_reward=NR, seed=seed, **kw).double()


def data(R, B, T, kind="bits", seed=1, lengths=None):
    """Random padded sequences y (R,B,T+1,Y) ∈ {0,1}, one-hot a (R,B,T,A), targets r, lengths (R,B)."""
    g = torch.Generator().manual_seed(seed)
    y = torch.randint(0, 2, (R, B, T + 1, Y), generator=g).double()
    a = F.one_hot(torch.randint(0, A, (R, B, T), generator=g), A).double()
    r = (
        torch.randint(0, 2, (R, B, T + 1, NR), generator=g).double()
        if kind == "bits"
        else torch.randn(R, B, T + 1, 1, generator=g, dtype=torch.float64)
    )
    if lengths is None:
        lengths = torch.randint(1, T + 1, (R, B), generator=g)
    return y, a, r, lengths


def reference(p: ElmanPredictor, r: int, y, a):
    """Eqs. (4.1–4.5) for run r and one unpadded sequence y (T+1, Y), a (T, A), step by step."""

    def sig(x, beta):
        return 1 / (1 + torch.exp(-beta * x))

    m = sig(p.b_init[r], p.beta_m)
    ms, ys, rs = [], [], []
    for t in range(len(y)):
        if t > 0:
            m = sig(
                p.W_my[r] @ (p.c_y * y[t - 1]) + p.W_ma[r] @ (p.c_a * a[t - 1]) + p.W_mm[r] @ m + p.b_m[r], p.beta_m
            )
        ms.append(m)
        ys.append(sig(p.W_ym[r] @ m + p.b_y[r], p.beta_y) if p.predict_obs else None)
        if p.reward_output == "bits":
            rs.append(sig(p.W_rm[r] @ m + p.b_r[r], p.beta_r))
        elif p.reward_output == "linear":
            rs.append(p.W_rm[r] @ m + p.b_r[r])
    return ms, ys, rs


@pytest.mark.parametrize("kind", KINDS)
def test_forward_matches_per_step_loop(kind):
    p = make(R=3, **kind)
    y, a, _, lengths = data(3, 4, 6, kind["reward_output"])
    with torch.no_grad():
        y_hat, r_hat, m = p.forward_sequences(y, a, lengths)
        for run in range(3):
            for b in range(4):
                T = int(lengths[run, b])
                ms, ys, rs = reference(p, run, y[run, b, : T + 1], a[run, b, :T])
                torch.testing.assert_close(m[run, b, : T + 1], torch.stack(ms))
                if p.predict_obs:
                    torch.testing.assert_close(y_hat[run, b, : T + 1], torch.stack(ys))
                if rs:
                    torch.testing.assert_close(r_hat[run, b, 1 : T + 1], torch.stack(rs[1:]))
    assert (y_hat is None) == (not p.predict_obs) and (r_hat is None) == (kind["reward_output"] == "none")


def test_online_step_matches_sequence_forward():
    """initial_state() + step() reproduce forward_sequences, as the actor phase uses them."""
    p = make(R=3)
    y, a, _, _ = data(3, 1, 5)
    lengths = torch.full((3, 1), 5)
    y_hat, r_hat, m_seq = p.forward_sequences(y, a, lengths)
    m = p.initial_state()
    y0 = p.outputs(m)[0]
    torch.testing.assert_close(m, m_seq[:, 0, 0])
    torch.testing.assert_close(y0, y_hat[:, 0, 0])
    for t in range(5):
        m = p.step(m, y[:, 0, t], a[:, 0, t])
        yh, rh = p.outputs(m)
        torch.testing.assert_close(m, m_seq[:, 0, t + 1])
        torch.testing.assert_close(yh, y_hat[:, 0, t + 1])
        torch.testing.assert_close(rh, r_hat[:, 0, t + 1])


def reference_loss(p, run, y, a, r):
    """Σ_t E_t of Eq. (4.6) / Eq. (5.2) for one unpadded sequence, from the per-step loop."""
    _, ys, rs = reference(p, run, y, a)

    def ce(x, xh):
        return -(x * torch.log(xh) + (1 - x) * torch.log(1 - xh)).sum()

    E = sum(p.rho_y * ce(y[t], ys[t]) for t in range(len(y))) if p.predict_obs else 0.0
    for t in range(1, len(y)):
        if p.reward_output == "bits":
            E = E + p.rho_r * ce(r[t], rs[t])
        elif p.reward_output == "linear":
            E = E + p.rho_r * 0.5 * ((r[t] - rs[t]) ** 2).sum()
    return E


@pytest.mark.parametrize("kind", KINDS)
def test_loss_matches_per_step_loop(kind):
    p = make(R=2, **kind)
    y, a, r, lengths = data(2, 3, 7, kind["reward_output"])
    with torch.no_grad():
        loss = p.loss(y, a, r if p.reward_output != "none" else None, lengths)
        for run in range(2):
            for b in range(3):
                T = int(lengths[run, b])
                torch.testing.assert_close(
                    loss[run, b], reference_loss(p, run, y[run, b, : T + 1], a[run, b, :T], r[run, b, : T + 1])
                )


def grad(p, y, a, r, lengths):
    p.zero_grad()
    p.loss(y, a, r, lengths).sum().backward()
    return [q.grad.clone() for q in p.parameters()]


@pytest.mark.parametrize("kind", KINDS)
def test_bptt_gradient_matches_finite_differences_and_ignores_padding(kind):
    """Autograd through the unrolled network (BPTT, §2.4.1) vs central differences in float64,
    on sequences of lengths 1, 3 and 7 padded to T = 7; padded values do not change it."""
    p = make(R=2, **kind)
    y, a, r, _ = data(2, 3, 7, kind["reward_output"])
    lengths = torch.tensor([[1, 3, 7], [7, 1, 3]])
    r = r if p.reward_output != "none" else None
    g = grad(p, y, a, r, lengths)
    eps = 1e-6
    with torch.no_grad():
        for q, gq in zip(p.parameters(), g):
            fd = torch.empty_like(q)
            for i in range(q.numel()):
                old = q.view(-1)[i].item()
                q.view(-1)[i] = old + eps
                up = p.loss(y, a, r, lengths).sum()
                q.view(-1)[i] = old - eps
                down = p.loss(y, a, r, lengths).sum()
                q.view(-1)[i] = old
                fd.view(-1)[i] = (up - down) / (2 * eps)
            torch.testing.assert_close(gq, fd, rtol=1e-6, atol=1e-7)
    # padded steps: t > T for y and r, t ≥ T for a
    t = torch.arange(8)
    pad = (t > lengths.unsqueeze(-1)).unsqueeze(-1)
    gen = torch.Generator().manual_seed(5)
    for fill in ("random", "nan"):

        def noise(x, fill=fill):
            return (
                torch.randn(x.shape, generator=gen, dtype=x.dtype) * 9
                if fill == "random"
                else torch.full_like(x, torch.nan)
            )

        y2 = torch.where(pad, noise(y), y)
        a2 = torch.where(pad[:, :, 1:], noise(a), a)
        r2 = torch.where(pad, noise(r), r) if r is not None else None
        for g1, g2 in zip(g, grad(p, y2, a2, r2, lengths)):
            torch.testing.assert_close(g1, g2, rtol=0, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_hand_written_bptt_equals_autograd(kind):
    """ElmanPredictor.gradients (BPTT written out, Eqs. 2.57–2.63, what train_epoch uses) = autograd
    of Σ_b w_b loss_b in float64, for sequences of lengths 1, 3 and 7 padded to 7 with random
    per-sequence weights w; NaN in the padding is cleaned away and changes nothing."""
    p = make(R=2, **kind)
    y, a, r, _ = data(2, 3, 7, kind["reward_output"])
    lengths = torch.tensor([[1, 3, 7], [7, 1, 3]])
    r = r if p.reward_output != "none" else None
    w = torch.rand(2, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) + 0.5
    auto = torch.autograd.grad((p.loss(y, a, r, lengths) * w).sum(), list(p.parameters()))
    pad = (torch.arange(8) > lengths.unsqueeze(-1)).unsqueeze(-1)
    y, a = torch.where(pad, torch.nan, y), torch.where(pad[:, :, 1:], torch.nan, a)
    r = torch.where(pad, torch.nan, r) if r is not None else None
    hand = p.gradients(*clean(y, a, r, lengths), lengths, w)
    assert len(hand) == len(auto)
    for (name, _), want, got in zip(p.named_parameters(), auto, hand):
        assert want.abs().max() > 0, name
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12, msg=name)


def test_pattern_mode_epoch_equals_sequential_sgd_of_single_runs():
    """train_epoch on R runs = for each run alone, SGD θ ← θ − α ∇ Σ_t E_t over its sequences in
    its own order, with single-run predictors built from the run's seed (seed + r)."""
    R, N, lr = 3, 5, 0.2
    batched = make(R=R, seed=10, lr=lr)
    y, a, r, lengths = data(R, N, 6)
    order = torch.stack([torch.randperm(N, generator=torch.Generator().manual_seed(k)) for k in range(R)])
    batched.train_epoch(y, a, r, lengths, order)
    for run in range(R):
        single = make(R=1, seed=10 + run, lr=lr)
        for i in order[run].tolist():
            T = int(lengths[run, i])
            loss = reference_loss(single, 0, y[run, i, : T + 1], a[run, i, :T], r[run, i, : T + 1])
            grads = torch.autograd.grad(loss, list(single.parameters()))
            with torch.no_grad():
                for q, gq in zip(single.parameters(), grads):
                    q -= lr * gq
        for (name, qb), qs in zip(batched.named_parameters(), single.parameters()):
            torch.testing.assert_close(qb[run], qs[0], msg=name)


@pytest.mark.parametrize("batch_size", [2, 3])
def test_batched_epoch_is_sgd_on_the_mean_loss_of_each_chunk(batch_size):
    """batch_size B: one step per B sequences of the run's order (the last chunk smaller), on the
    mean of their losses, each computed by the per-step reference loop on its unpadded sequence."""
    R, N, lr = 2, 7, 0.2
    batched = make(R=R, seed=20, lr=lr, batch_size=batch_size)
    y, a, r, lengths = data(R, N, 6, seed=4)
    order = torch.stack([torch.randperm(N, generator=torch.Generator().manual_seed(k)) for k in range(R)])
    batched.train_epoch(y, a, r, lengths, order)
    for run in range(R):
        single = make(R=1, seed=20 + run, lr=lr)
        chunks = order[run].split(batch_size)
        for chunk in chunks:
            losses = [
                reference_loss(
                    single,
                    0,
                    y[run, i, : int(lengths[run, i]) + 1],
                    a[run, i, : int(lengths[run, i])],
                    r[run, i, : int(lengths[run, i]) + 1],
                )
                for i in chunk.tolist()
            ]
            grads = torch.autograd.grad(torch.stack(losses).mean(), list(single.parameters()))
            with torch.no_grad():
                for q, gq in zip(single.parameters(), grads):
                    q -= lr * gq
        for (name, qb), qs in zip(batched.named_parameters(), single.parameters()):
            torch.testing.assert_close(qb[run], qs[0], msg=name)


def test_predictor_batch_equals_training_each_alone():
    """Chapter 5's observation and scalar-reward predictors trained as one PredictorBatch (their
    memories in one batch, heads apart) end with the parameters each gets trained alone on the
    same sequences in its own order, for 3 epochs."""
    R, N = 2, 6
    obs = dict(reward_output="none", time_average=True, lr=0.1)
    rew = dict(reward_output="linear", predict_obs=False, time_average=True, lr=0.1)
    y, a, _, lengths = data(R, N, 7, seed=6)
    r = torch.randn(R, N, 8, 1, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    batch = [make(R=R, seed=30, **obs), make(R=R, seed=40, **rew)]
    alone = [make(R=R, seed=30, **obs), make(R=R, seed=40, **rew)]
    g = torch.Generator().manual_seed(8)
    for _ in range(3):
        orders = [torch.rand(R, N, generator=g).argsort(1) for _ in batch]
        PredictorBatch(batch, y, a, [None, r], lengths).train_epoch(orders)
        for p, target, order in zip(alone, (None, r), orders):
            p.train_epoch(y, a, target, lengths, order)
    for b, s in zip(batch, alone):
        for (name, qb), qs in zip(b.named_parameters(), s.parameters()):
            assert not torch.equal(
                qb, make(R=R, seed=30 if b.predict_obs else 40, **(obs if b.predict_obs else rew)).get_parameter(name)
            )
            torch.testing.assert_close(qb, qs, rtol=1e-12, atol=1e-12, msg=name)


def test_predictor_batch_needs_the_same_memory():
    with pytest.raises(ValueError, match="same memory"):
        PredictorBatch(
            [make(R=2), make(R=2, c_y=0.5)], *data(2, 3, 4)[:2], [None, None], torch.ones(2, 3, dtype=torch.long)
        )


def test_runs_are_independent():
    """Run 0's parameters after training depend on run 0's data only."""
    R, N = 3, 6
    y, a, r, lengths = data(R, N, 7, seed=2)
    y2, a2, r2, lengths2 = data(R, N, 7, seed=3)
    order = torch.stack([torch.randperm(N, generator=torch.Generator().manual_seed(k)) for k in range(R)])
    order2 = torch.stack([torch.randperm(N, generator=torch.Generator().manual_seed(9 + k)) for k in range(R)])

    def keep(u, v):
        return torch.cat([u[:1], v[1:]])

    runs = []
    for data_ in (
        (y, a, r, lengths, order),
        tuple(keep(u, v) for u, v in zip((y, a, r, lengths, order), (y2, a2, r2, lengths2, order2))),
    ):
        p = make(R=R, seed=4, lr=0.1)
        for _ in range(3):
            p.train_epoch(*data_)
        runs.append([q.detach()[0] for q in p.parameters()])
    assert not torch.equal(lengths[1:], lengths2[1:])
    for q1, q2 in zip(*runs):
        torch.testing.assert_close(q1, q2, rtol=1e-12, atol=1e-12)


def test_learns_deterministic_sequences():
    """Two length-4 sequences whose observation y_t is the one-hot of a_{t−1} (y_0 fixed), with a
    reward bit at the last step only (so the memory must count): the Eq. (4.8) error, summed over
    the 6 outputs, falls from ≈ 3 (random init) to < 0.05 per step on average, i.e. each output is
    within ~0.01 of its target (reaches ≈ 0.02 after 300 epochs at α = 0.3)."""
    actions = torch.tensor([[0, 1, 2, 1], [2, 2, 0, 1]])
    a = F.one_hot(actions, 3).double().expand(2, -1, -1, -1)  # the same two sequences in both runs
    y0 = torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(2, 1, 4)
    y = torch.cat([y0, F.one_hot(actions, 4).double()], 1).expand(2, -1, -1, -1)
    r = torch.zeros(2, 2, 5, 2, dtype=torch.float64)
    r[:, :, 1:4, 0] = 1
    r[:, :, 4, 1] = 1
    lengths = torch.full((2, 2), 4)
    p = ElmanPredictor(2, 4, 3, n_memory=8, n_reward=2, lr=0.3, seed=0).double()
    before = p.prediction_errors(y, a, r, lengths).mean()
    order = torch.tensor([[0, 1], [1, 0]])
    for _ in range(300):
        p.train_epoch(y, a, r, lengths, order)
    after = p.prediction_errors(y, a, r, lengths)
    assert before > 1.0
    assert after.mean() < 0.05 and after.mean() < 0.1 * before, (before, after)


def test_prediction_errors_eq_4_8_and_nan_padding():
    p = make(R=2)
    y, a, r, lengths = data(2, 3, 5)
    err = p.prediction_errors(y, a, r, lengths)
    y_hat, r_hat, _ = p.forward_sequences(y, a, lengths)
    for run in range(2):
        for b in range(3):
            T = int(lengths[run, b])
            expect = p.rho_y * (y - y_hat)[run, b].abs().sum(-1) + p.rho_r * (r - r_hat)[run, b].abs().sum(-1)
            expect[0] = p.rho_y * (y - y_hat)[run, b, 0].abs().sum()
            torch.testing.assert_close(err[run, b, : T + 1], expect[: T + 1])
            assert torch.isnan(err[run, b, T + 1 :]).all()


def test_init_is_per_run_seeded_unit_gaussian():
    """Run r's initial parameters depend on seed + r only (not on n_runs); N(0, 1) by default."""
    big = ElmanPredictor(4, 7, 4, n_reward=4, seed=3)
    small = ElmanPredictor(2, 7, 4, n_reward=4, seed=5)
    for qb, qs in zip(big.parameters(), small.parameters()):
        torch.testing.assert_close(qb[2:], qs)
    flat = torch.cat([q.detach().flatten() for q in big.parameters()])
    assert abs(flat.mean()) < 0.1 and abs(flat.std() - 1) < 0.1


def test_reward_targets_bits_and_scalar():
    """Scalar rewards r_1 … r_T → one bit per reward value (§4.2 fn. 1) or the scalar (Eq. 5.2),
    shifted so index t holds r_t; padding (reward 0) codes as all-zero bits."""
    env = SimpleNamespace(reward_values=(-5.0, -1.0, -0.1, 5.0))
    rewards = torch.tensor([[[-0.1, -1.0, 5.0, 0.0]]], dtype=torch.float64)
    bits = ElmanPredictor(1, Y, A, n_reward=4, reward_output="bits").reward_targets(env.reward_values, rewards)
    assert bits.shape == (1, 1, 5, 4)
    assert bits[0, 0].tolist() == [[0, 0, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0]]
    scalar = ElmanPredictor(1, Y, A, reward_output="linear").reward_targets(env.reward_values, rewards)
    assert scalar[0, 0, :, 0].tolist() == [0.0, -0.1, -1.0, 5.0, 0.0]
    assert ElmanPredictor(1, Y, A, reward_output="none").reward_targets(env.reward_values, rewards) is None
