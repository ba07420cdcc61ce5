"""The transformer memory (ferl/predictors/transformer.py): its batched unroll against a per-run
reference written from the module docstring with torch.nn.functional.scaled_dot_product_attention
and NumPy's sinusoids; causal masking (a change at step t + k moves no memory before it, padding
moves nothing); the online step with its key/value cache = the unroll; training through autograd
lowers the loss and recalls a bit, runs and members train apart, and online training through
train.py lowers the prediction error; the context checked against the environment's T_max."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import run_train
from ferl.config.params import ConfigError, check_arguments
from ferl.predictors.recurrent import predictor
from ferl.predictors.training import PredictorBatch
from ferl.predictors.transformer import TransformerPredictor
from ferl.trainers.facts import facts_for
from five_arms import FiveArms
from test_sizes import only_error_line

Y, A, NR = 4, 3, 2


def make(R=3, M=6, layers=2, heads=2, context=9, seed=0, **kw):
    return predictor(
        memory="transformer",
        n_runs=R,
        n_obs=Y,
        n_actions=A,
        n_memory=M,
        n_reward=NR,
        layers=layers,
        heads=heads,
        context=context,
        seed=seed,
        c_y=0.7,
        c_a=1.3,
        **kw,
    ).double()


def data(R, B, T, seed=1):
    g = torch.Generator().manual_seed(seed)
    y = torch.randint(0, 2, (R, B, T + 1, Y), generator=g).double()
    a = F.one_hot(torch.randint(0, A, (R, B, T), generator=g), A).double()
    return y, a


def sinusoids(n: int, d: int) -> torch.Tensor:
    """p_{s,2i} = sin(s/10000^{2i/d}), p_{s,2i+1} = cos(…), s = 0 … n−1, in NumPy."""
    s, i = np.arange(n)[:, None], np.arange(d)[None, :]
    angle = s / 10000.0 ** ((i - i % 2) / d)
    return torch.from_numpy(np.where(i % 2 == 0, np.sin(angle), np.cos(angle)))


def reference(p, run: int, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """m_0 … m_T (T+1, M) of one unpadded sequence y (T+1, Y), a (T, A), run ``run``'s weights alone:
    the equations of the module docstring with torch's own layer norm and causal attention."""
    P = {name: q[run] for name, q in p.named_parameters()}
    M, H, T = p.memory_size, p.attention.heads, a.shape[0]
    u = torch.cat([torch.zeros(1, Y + A, dtype=y.dtype), torch.cat([p.c_y * y[:-1], p.c_a * a], 1)])
    x = u @ P["W_in"].T + P["b_in"] + sinusoids(T + 1, M)
    for layer in range(p.layers):
        h = F.layer_norm(x, (M,), P["ln1_g"][layer], P["ln1_b"][layer])
        q, k, v = (h @ P["W_qkv"][layer].T + P["b_qkv"][layer]).split(M, 1)
        heads = [
            F.scaled_dot_product_attention(*(z[:, j * M // H : (j + 1) * M // H] for z in (q, k, v)), is_causal=True)
            for j in range(H)
        ]
        x = x + torch.cat(heads, 1) @ P["W_o"][layer].T + P["b_o"][layer]
        h = F.layer_norm(x, (M,), P["ln2_g"][layer], P["ln2_b"][layer])
        x = x + F.gelu(h @ P["W_1"][layer].T + P["b_1"][layer]) @ P["W_2"][layer].T + P["b_2"][layer]
    return torch.tanh(F.layer_norm(x, (M,), P["lnf_g"], P["lnf_b"]))


def perturbed_weights(p, seed=5):
    """Biases and LN parameters away from their initial 0 and 1, so the reference checks them too."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for q in p.memory_parameters():
            q.add_(0.3 * torch.randn(q.shape, generator=g, dtype=q.dtype))
    return p


def test_batched_unroll_equals_a_per_run_reference():
    p = perturbed_weights(make(R=3, M=6, layers=2, heads=2))
    y, a = data(3, 2, 7)
    with torch.no_grad():
        m = p.unroll(y, a)
    assert m.shape == (3, 2, 8, 6)
    for run in range(3):
        for b in range(2):
            torch.testing.assert_close(m[run, b], reference(p, run, y[run, b], a[run, b]))


def test_a_change_at_step_t_moves_no_memory_before_it():
    """Perturb the input at step s (y_s or a_s, read by m_{s+1}): m_0 … m_s are unchanged, m_{s+1} moves."""
    p = perturbed_weights(make())
    y, a = data(3, 2, 8)
    with torch.no_grad():
        m = p.unroll(y, a)
        for s in (0, 3, 7):
            y2, a2 = y.clone(), a.clone()
            y2[:, :, s] += 2.0
            a2[:, :, s] = a2[:, :, s].roll(1, -1)
            for moved in (p.unroll(y2, a), p.unroll(y, a2)):
                assert torch.equal(moved[:, :, : s + 1], m[:, :, : s + 1])
                assert (moved[:, :, s + 1] - m[:, :, s + 1]).abs().amax() > 1e-3


def test_padded_sequences_give_the_unpadded_memories():
    """Sequences of 2, 5 and 8 steps padded to 8 with arbitrary values: each one's m_0 … m_T equal
    its unroll alone; the padding is never attended to."""
    p = perturbed_weights(make())
    y, a = data(3, 3, 8)
    g = torch.Generator().manual_seed(9)
    lengths = [2, 5, 8]
    for b, T in enumerate(lengths):
        y[:, b, T + 1 :] = torch.randn(y[:, b, T + 1 :].shape, generator=g, dtype=y.dtype) * 5
        a[:, b, T:] = torch.randn(a[:, b, T:].shape, generator=g, dtype=a.dtype) * 5
    with torch.no_grad():
        m = p.unroll(y, a)
        for b, T in enumerate(lengths):
            alone = p.unroll(y[:, b : b + 1, : T + 1], a[:, b : b + 1, :T])
            torch.testing.assert_close(m[:, b : b + 1, : T + 1], alone, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("layers, heads, T", [(1, 1, 9), (2, 3, 9), (2, 2, 4)])
def test_online_step_with_its_cache_equals_the_unroll(layers, heads, T):
    """initial_state, then ``step`` T times (T = context: the cache full), gives m_0 … m_T of ``unroll``."""
    p = perturbed_weights(make(M=6, layers=layers, heads=heads, context=9))
    y, a = data(3, 1, T)
    with torch.no_grad():
        m = p.unroll(y, a)[:, 0]
        state = p.initial_state()
        assert state[0].shape == (3, 6 + 1) and state[1].shape == (3, layers, 2, 10, 6)
        got = [p.memory(state)]
        for t in range(T):
            state = p.step(state, y[:, 0, t], a[:, 0, t])
            got.append(p.memory(state))
    torch.testing.assert_close(torch.stack(got, 1), m)


def test_a_sequence_longer_than_the_context_is_refused():
    p = make(context=4)
    y, a = data(3, 1, 5)
    with pytest.raises(ValueError, match="context=4 is shorter than the sequences' 5 steps"):
        p.unroll(y, a)


def test_training_lowers_the_loss_and_recalls_a_bit():
    """Plain SGD through autograd (``PredictorBatch``), 2 runs, 8 epochs of 48 sequences whose first
    observation is a random bit and whose last reward bit repeats it 6 steps later: the held-out
    loss falls below a tenth of its first value and the bit is recalled (chance 0.5)."""
    from test_memories import delayed_bit, recall_predictor, trained_on_delayed_bits

    R, delay = 2, 6
    p = recall_predictor("transformer", R, n_memory=12, lr=0.02, context=delay)
    with torch.no_grad():
        first = p.loss(*delayed_bit(R, 200, delay, seed=2)[:4]).mean(1)
    y, a, r, lengths, bit = trained_on_delayed_bits(p, R, 48, delay, epochs=8)
    with torch.no_grad():
        last = p.loss(y, a, r, lengths).mean(1)
        _, r_hat, _ = p.forward_sequences(y, a, lengths)
    assert (last < 0.1 * first).all(), (first, last)
    accuracy = ((r_hat[:, :, -1, 0] > 0.5).long() == bit).double().mean(1)
    assert (accuracy > 0.95).all(), accuracy


def test_context_heads_and_layers_are_checked():
    with pytest.raises(ConfigError, match=r"^predictor\.joint\.heads=4 is not allowed: a divisor of n_memory=6"):
        check_arguments(predictor, {"memory": "transformer", "n_memory": 6, "heads": 4}, "predictor.joint.")
    with pytest.raises(
        ConfigError, match=r"^predictor\.joint\.context=9 is not allowed: ≥ 10, the environment's T_max"
    ):
        check_arguments(predictor, {"memory": "transformer", "context": 9, "max_steps": 10}, "predictor.joint.")
    with pytest.raises(ConfigError, match=r"^predictor\.joint\.layers=5 is not allowed"):
        check_arguments(predictor, {"memory": "transformer", "layers": 5}, "predictor.joint.")
    check_arguments(predictor, {"memory": "transformer", "context": 10, "max_steps": 10}, "predictor.joint.")
    # the environment's T_max is the context where none is stated
    p = predictor(memory="transformer", n_runs=1, n_obs=Y, n_actions=A, n_reward=NR, max_steps=13)
    assert isinstance(p, TransformerPredictor) and p.context == 13 and p.describe()["context"] == 13
    with pytest.raises(ValueError, match="context is needed"):
        predictor(memory="transformer", n_runs=1, n_obs=Y, n_actions=A, n_reward=NR)


def test_a_context_shorter_than_the_mazes_t_max_is_one_line_before_any_file(tmp_path):
    """The regular maze of corridor 3 lasts at most T_max = 10 steps (table4_1_regular): context 9 is refused."""
    run_dir = tmp_path / "out" / "run"
    result = run_train(
        "experiment=table4_1_regular",
        "trainer=online",
        "predictor.joint.memory=transformer",
        "+predictor.joint.context=9",
        f"hydra.run.dir={run_dir}",
    )
    assert only_error_line(result) == (
        "ferl: error: predictor.joint.context=9 is not allowed: ≥ 10, the environment's "
        "T_max (env.max_steps): the memory attends to the whole episode"
    )
    assert not (tmp_path / "out").exists()


def test_online_training_through_train_py_lowers_the_prediction_error(tmp_path):
    """The online trainer (trainer=online) on the regular maze of corridor 3, 2 runs × 300 episodes
    at α = 0.02: the memory's context is the maze's T_max = 10 (run.json) and each run's prediction
    error over its last 50 episodes is below half of its first 20's (the memory learns while the
    agent acts; whether the agent then solves the maze is measured in docs/beyond.md). Over seeds
    0-3 that ratio ranged 0.04-0.33 per run, so half leaves room for the random stream to move;
    a memory that did not learn stays near 1."""
    run_dir = tmp_path / "run"
    result = run_train(
        "experiment=table4_1_regular",
        "trainer=online",
        "predictor.joint.memory=transformer",
        "predictor.joint.lr=0.02",
        "n_runs=2",
        "trainer.n_episodes=300",
        "trainer.log_every=100",
        "trainer.final_window=100",
        f"hydra.run.dir={run_dir}",
    )
    assert result.returncode == 0, result.stderr[-3000:]
    joint = json.loads((run_dir / "records" / "run.json").read_text())["predictors"]["joint"]
    assert (joint["kind"], joint["context"], joint["layers"], joint["heads"]) == ("transformer", 10, 1, 1)
    error = np.load(run_dir / "records" / "online.npz")["prediction_error"]
    assert error.shape == (2, 300) and np.isfinite(error).all()
    assert (error[:, -50:].mean(1) < 0.5 * error[:, :20].mean(1)).all(), error


def test_runs_and_members_train_apart():
    """One epoch of 2 runs × 2 members (chapter 5's observation and reward predictors, one
    ``PredictorBatch`` along the run axis) = each (run, member) trained alone in a 1-run predictor
    holding its parameters, on its sequences in its order: runs and members share nothing."""
    y, a = data(2, 5, 6)
    r = torch.randint(0, 2, (2, 5, 7, NR), generator=torch.Generator().manual_seed(3)).double()
    lengths = torch.tensor([[6, 2, 4, 5, 1], [3, 6, 6, 2, 4]])
    members = [make(R=2, M=4, layers=1, heads=2, seed=s, lr=0.1, batch_size=2) for s in (0, 7)]
    orders = [
        torch.stack([torch.randperm(5, generator=torch.Generator().manual_seed(10 * k + run)) for run in range(2)])
        for k in range(2)
    ]
    alone = []
    for k, member in enumerate(members):
        for run in range(2):
            single = make(R=1, M=4, layers=1, heads=2, lr=0.1, batch_size=2)
            with torch.no_grad():
                for q, source in zip(single.parameters(), member.parameters()):
                    q.copy_(source[run : run + 1])
            PredictorBatch(
                [single], y[run : run + 1], a[run : run + 1], [r[run : run + 1]], lengths[run : run + 1]
            ).train_epoch([orders[k][run : run + 1]])
            alone.append([q[0] for q in single.parameters()])
    before = [[q.detach().clone() for q in member.parameters()] for member in members]
    PredictorBatch(members, y, a, [r, r], lengths).train_epoch(orders)
    assert all(not torch.equal(q, q0) for member, b in zip(members, before) for q, q0 in zip(member.parameters(), b))
    for k, member in enumerate(members):
        for run in range(2):
            for q, want in zip(member.parameters(), alone[2 * k + run]):
                torch.testing.assert_close(q[run], want)


def test_the_job_hands_t_max_to_the_transformer_alone():
    """``max_steps`` is a fact of the environment (ferl/trainers/facts.py) that only a constructor
    taking it gets; stated against the environment, it is refused."""
    env = FiveArms(2, torch.Generator().manual_seed(0))
    node = {"_target_": "ferl.predictors.recurrent.predictor", "memory": "transformer"}
    assert facts_for(node, "predictor.joint", env) == {"n_reward": 3, "max_steps": env.max_steps}
    assert "max_steps" not in facts_for({**node, "memory": "gru"}, "predictor.joint", env)
    with pytest.raises(
        ConfigError,
        match=rf"^predictor\.joint\.max_steps=99 disagrees with the environment: .* "
        rf"has episodes of at most {env.max_steps} steps; leave it out",
    ):
        facts_for({**node, "max_steps": 99}, "predictor.joint", env)


def test_qk_normalised_attention_equals_numpy_and_bounds_every_logit():
    """softmax(g q̂ k̂ᵀ + mask) v per head (``Attention.qk_norm`` g) against NumPy, with queries and
    keys scaled 1000× so that plain attention would be one-hot: QK-normalised logits stay in [−g, g]."""
    from ferl.predictors.transformer import Attention, attend

    g, heads, n, d = 3.0, 2, 5, 6
    gen = torch.Generator().manual_seed(3)
    q, k, v = (torch.randn(n, d, generator=gen, dtype=torch.float64) for _ in range(3))
    causal = torch.ones(n, n, dtype=torch.bool).tril()
    got = attend(q * 1000, k * 1000, v, causal, Attention(heads, g)).numpy()
    expected = np.zeros((n, d))
    for h in range(heads):
        part = slice(h * d // heads, (h + 1) * d // heads)
        qh, kh = q[:, part].numpy(), k[:, part].numpy()
        qh = qh / np.linalg.norm(qh, axis=1, keepdims=True)
        kh = kh / np.linalg.norm(kh, axis=1, keepdims=True)
        logits = g * qh @ kh.T
        assert np.abs(logits).max() <= g + 1e-12
        logits = np.where(np.tril(np.ones((n, n))) > 0, logits, -np.inf)
        weights = np.exp(logits - logits.max(1, keepdims=True))
        expected[:, part] = (weights / weights.sum(1, keepdims=True)) @ v[:, part].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
    plain = attend(q * 1000, k * 1000, v, causal, Attention(heads)).numpy()
    assert not np.allclose(plain, expected, atol=1e-3)  # the option changes what is computed


def test_the_qk_normalised_step_with_its_cache_equals_the_unroll():
    p = perturbed_weights(make(M=6, layers=2, heads=2, context=9, qk_norm=4.0))
    y, a = data(3, 1, 9)
    with torch.no_grad():
        m = p.unroll(y, a)[:, 0]
        state, got = p.initial_state(), []
        got.append(p.memory(state))
        for t in range(9):
            state = p.step(state, y[:, 0, t], a[:, 0, t])
            got.append(p.memory(state))
    torch.testing.assert_close(torch.stack(got, 1), m)
    assert p.describe()["qk_norm"] == 4.0
