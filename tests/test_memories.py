"""Memories beyond the Elman layer (§5.4): LSTM, GRU, echo-state and transformer predictors against
references written from their equations (the transformer's in tests/test_transformer.py), their
training gradients against central finite differences on padded sequences, the reservoir's
spectral radius against NumPy, the memory chosen by name, and a memory that lasts: LSTM and GRU
keep a bit over 12 steps."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ferl.config.params import ConfigError, check_arguments
from ferl.predictors.echo_state import EchoStatePredictor
from ferl.predictors.gated import GRUPredictor, LSTMPredictor
from ferl.predictors.heads import clean
from ferl.predictors.recurrent import predictor
from ferl.predictors.training import PredictorBatch
from test_transformer import reference as transformer_reference

Y, A, M, NR = 4, 3, 3, 2
KW = dict(n_memory=M, n_reward=NR, c_y=0.7, c_a=1.3, beta_y=1.2, beta_r=0.9, rho_y=1.5, rho_r=2.5, init_std=0.7)


def make(memory, R=2, seed=0, **kw):
    if memory == "transformer":
        kw.setdefault("context", 8)  # the sequences' longest
    return predictor(memory=memory, n_runs=R, n_obs=Y, n_actions=A, seed=seed, **{**KW, **kw}).double()


def data(R, B, T, seed=1):
    g = torch.Generator().manual_seed(seed)
    y = torch.randint(0, 2, (R, B, T + 1, Y), generator=g).double()
    a = F.one_hot(torch.randint(0, A, (R, B, T), generator=g), A).double()
    r = torch.randint(0, 2, (R, B, T + 1, NR), generator=g).double()
    return y, a, r


def reference_memory(p, run: int, y, a) -> list:
    """h_0 … h_T of one unpadded sequence, step by step from the module docstrings' equations."""
    if p.kind == "transformer":
        return list(transformer_reference(p, run, y[: len(a) + 1], a))
    sig = torch.sigmoid
    if p.kind != "esn":
        W, U, b = p.W[run], p.U[run], p.b[run]
    h = torch.zeros(M, dtype=torch.float64)
    c, out = torch.zeros(M, dtype=torch.float64), [torch.zeros(M, dtype=torch.float64)]
    for t in range(len(a)):
        u = torch.cat([p.c_y * y[t], p.c_a * a[t]])
        if p.kind == "lstm":
            z = W @ u + U @ h + b
            i, f, g, o = sig(z[:M]), sig(z[M : 2 * M]), torch.tanh(z[2 * M : 3 * M]), sig(z[3 * M :])
            c = f * c + i * g
            h = o * torch.tanh(c)
        elif p.kind == "gru":
            x, hh = W @ u + b, U @ h
            r, z = sig(x[:M] + hh[:M]), sig(x[M : 2 * M] + hh[M : 2 * M])
            n = torch.tanh(x[2 * M :] + r * (hh[2 * M :] + p.b_hn[run]))
            h = (1 - z) * n + z * h
        else:  # esn
            lam = p.leak_rate
            h = (1 - lam) * h + lam * torch.tanh(p.W_in[run] @ u + p.W_res[run] @ h)
        out.append(h)
    return out


@pytest.mark.parametrize("memory", ["lstm", "gru", "esn", "transformer"])
def test_unroll_and_online_step_match_the_equations(memory):
    p = make(memory, R=2)
    y, a, _ = data(2, 3, 5)
    with torch.no_grad():
        m = p.unroll(y, a)
        state = p.initial_state()
        for t in range(5):
            state = p.step(state, y[:, 1, t], a[:, 1, t])
            torch.testing.assert_close(p.memory(state), m[:, 1, t + 1])
    for run in range(2):
        want = torch.stack(reference_memory(p, run, y[run, 2], a[run, 2]))
        torch.testing.assert_close(m[run, 2], want)


@pytest.mark.parametrize("memory", ["lstm", "gru", "esn", "transformer"])
@pytest.mark.parametrize("time_average", [False, True])
def test_training_gradients_equal_finite_differences_on_padded_sequences(memory, time_average):
    """``gradients`` (what training applies: autograd through the unrolled LSTM/GRU/transformer, the readout's
    gradients written out for the ESN) = central differences of Σ_b w_b loss_b, float64, every
    trained entry; sequences of lengths 1, 4 and 6 padded to 6, NaN in the padding."""
    p = make(memory, R=2, time_average=time_average)
    y, a, r = data(2, 3, 6)
    lengths = torch.tensor([[1, 4, 6], [6, 1, 4]])
    w = torch.tensor([[0.7, 1.3, 1.0], [1.1, 0.6, 0.9]], dtype=torch.float64)
    if time_average:
        w = w / (lengths + 1)  # J(T): each sequence's Σ_t E_t over T + 1
    pad = (torch.arange(7) > lengths.unsqueeze(-1)).unsqueeze(-1)
    noisy = torch.where(pad, torch.nan, y), torch.where(pad[:, :, 1:], torch.nan, a), torch.where(pad, torch.nan, r)
    got = p.gradients(*clean(*noisy, lengths), lengths, w)
    params = list(p.parameters())
    assert len(got) == len(params)

    def objective() -> float:
        return float((p.loss(y, a, r, lengths) * (lengths + 1 if time_average else 1) * w).sum())

    eps = 1e-6
    with torch.no_grad():
        for q, g in zip(params, got):
            assert g.abs().max() > 0
            flat, grad = q.view(-1), g.reshape(-1)
            for i in range(flat.numel()):
                keep = flat[i].item()
                flat[i] = keep + eps
                up = objective()
                flat[i] = keep - eps
                down = objective()
                flat[i] = keep
                assert abs((up - down) / (2 * eps) - grad[i].item()) < 1e-6 * max(1.0, abs(grad[i].item()))


def test_reservoir_has_its_spectral_radius_and_stays_fixed():
    p = make("esn", R=3, n_memory=12, spectral_radius=0.8, density=0.5)
    for run in range(3):
        assert np.abs(np.linalg.eigvals(p.W_res[run].numpy())).max() == pytest.approx(0.8, rel=1e-6)
        assert 0.2 < (p.W_res[run] != 0).double().mean() < 0.8
    before = p.W_res.clone(), p.W_in.clone()
    y, a, r = data(3, 4, 5)
    lengths = torch.full((3, 4), 5)
    p.train_epoch(y, a, r, lengths, torch.arange(4).expand(3, -1))
    assert torch.equal(p.W_res, before[0]) and torch.equal(p.W_in, before[1])
    assert [n for n, _ in p.named_parameters()] == ["W_ym", "b_y", "W_rm", "b_r"]


def test_memory_is_chosen_by_name_and_checked_as_that_class():
    assert isinstance(make("lstm"), LSTMPredictor) and isinstance(make("gru"), GRUPredictor)
    assert isinstance(make("esn"), EchoStatePredictor)
    assert make("lstm").memory_size == M and make("lstm").initial_state().shape == (2, 2 * M)
    with pytest.raises(
        ConfigError, match=r"predictor.joint.memory='tcn' is not allowed: one of elman, esn, gru, lstm, transformer"
    ):
        check_arguments(predictor, {"memory": "tcn"}, "predictor.joint.")
    with pytest.raises(ConfigError, match=r"predictor.joint.spectral_radius is not allowed"):
        check_arguments(predictor, {"memory": "gru", "spectral_radius": 0.9}, "predictor.joint.")
    with pytest.raises(ConfigError, match=r"beta_m=2.0 is not allowed: 1 with memory=lstm"):
        check_arguments(predictor, {"memory": "lstm", "beta_m": 2.0}, "predictor.joint.")


def delayed_bit(R: int, N: int, delay: int, seed: int):
    """Sequences whose first observation shows a bit (y_0 = e_0 or e_1), then blank steps (e_2) up
    to a recall cue (e_3) at t = delay − 1; the reward bit at t = delay, after the cue, is the bit
    shown ``delay`` steps earlier, every other reward target 0."""
    g = torch.Generator().manual_seed(seed)
    bit = torch.randint(0, 2, (R, N), generator=g)
    y = torch.zeros(R, N, delay + 1, Y)
    y[..., 2] = 1.0
    y[:, :, 0] = F.one_hot(bit, Y).float()
    y[:, :, delay - 1] = F.one_hot(torch.tensor(3), Y).float()
    a = F.one_hot(torch.zeros(R, N, delay, dtype=torch.long), A).float()
    r = torch.zeros(R, N, delay + 1, NR)
    r[:, :, -1, 0] = bit.float()
    return y, a, r, torch.full((R, N), delay), bit


def recall_predictor(memory: str, R: int, **kw):
    """A predictor of the reward bit alone (ρ_y = 0), trained on the plain sum Σ_t E_t, seed 4."""
    return predictor(
        memory=memory, n_runs=R, n_obs=Y, n_actions=A, n_reward=NR, seed=4, rho_y=0.0, time_average=False, **kw
    )


def trained_on_delayed_bits(p, R: int, n: int, delay: int, epochs: int):
    """Train ``p`` (R runs) for ``epochs`` pattern-mode epochs on n ``delayed_bit`` sequences, each
    run in its own random order; returns 200 fresh sequences (y, a, r, lengths, bit) to test it on."""
    y, a, r, lengths, _ = delayed_bit(R, n, delay, seed=0)
    batch = PredictorBatch([p], y, a, [r], lengths)
    g = torch.Generator().manual_seed(1)
    for _ in range(epochs):
        batch.train_epoch([torch.rand(R, n, generator=g).argsort(1)])
    return delayed_bit(R, 200, delay, seed=2)


@pytest.mark.parametrize("memory", ["lstm", "gru"])
def test_gated_memory_keeps_a_bit_over_twelve_steps(memory):
    """After 30 pattern-mode epochs on 64 sequences (float32, 2 runs), the memory recalls at the
    cue the bit shown 12 steps earlier, on fresh sequences (chance: 0.5)."""
    delay, R = 12, 2
    p = recall_predictor(memory, R, n_memory=8, lr=0.3)
    y, a, _, lengths, bit = trained_on_delayed_bits(p, R, 64, delay, epochs=30)
    with torch.no_grad():
        _, r_hat, _ = p.forward_sequences(y, a, lengths)
    accuracy = ((r_hat[:, :, -1, 0] > 0.5).long() == bit).double().mean(1)
    assert (accuracy > 0.95).all(), accuracy
