"""The predictors' BPTT in chunks of time steps (``ferl.predictors.training.chunked_bptt``): the
memory's steps in graphs of a fixed number of steps, the state carried, autograd back through them.

Checked against the memory class's own ``bptt`` (the Elman memory's written out, Eqs. 2.57–2.63;
the gated memories' ``autograd_bptt``: one vector-Jacobian product of the whole unroll), float64,
on padded sequences of lengths 11, 51 and 201, so that a chunk's padding and the carried state
both matter; compiled, one graph serves every length; a fused epoch in time chunks equals eager.
"""

import pytest
import torch
from torch._dynamo.utils import counters

from ferl.compiled import compiled
from ferl.predictors import training
from ferl.predictors.heads import clean, valid_steps
from ferl.predictors.recurrent import memory_class
from ferl.predictors.training import PredictorBatch, chunked_bptt, memory_steps
from test_predictor import GAINS, NR, A, M, Y, data

CPU = torch.device("cpu")


def gains(memory: str) -> dict:
    """The test gains; β_m (the Elman sigmoid's gain) only for the Elman memory."""
    return GAINS if memory == "elman" else {k: v for k, v in GAINS.items() if k != "beta_m"}


def predictor(memory: str, R: int = 2, seed: int = 0, **kw):
    """A float64 predictor of ``memory`` with observation and reward-bit heads."""
    return memory_class(memory)(
        R, Y, A, n_memory=M, n_reward=NR, seed=seed, init_std=0.7, **gains(memory), **kw
    ).double()


def batch_args(p, T: int, seed: int):
    """``bptt``'s arguments for 3 padded sequences per run of lengths ≤ T, the longest T."""
    y, a, r, lengths = data(2, 3, T, seed=seed)
    lengths[0, 0] = T
    y, a, r = clean(y, a, r, lengths)
    steps = valid_steps(lengths, T + 1) * torch.rand(2, 3, 1, dtype=torch.float64)
    reward_steps = steps * (torch.arange(T + 1) > 0)
    return y, a, [r], steps, reward_steps


@pytest.mark.parametrize("memory", ["elman", "lstm", "gru"])
@pytest.mark.parametrize("T", [11, 51, 201])
def test_chunked_bptt_equals_the_memory_s_own_bptt(memory, T):
    """Eager chunks (``memory_steps``) against the class's ``bptt``: every gradient, 1e-10."""
    p = predictor(memory)
    args = batch_args(p, T, seed=T)
    want = type(p).bptt([p], p.memory_parameters(), *args)
    got = chunked_bptt(memory_steps, [p], p.memory_parameters(), *args)
    assert len(got) == len(want) == len(list(p.parameters()))
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-10, atol=1e-12)


def test_compiled_chunks_serve_every_length_with_one_graph():
    """The LSTM's chunk compiled: the gradients of the class's ``bptt`` at T = 11 (float64, within
    the rounding of the generated kernels), and T = 51 and 201 compile nothing more."""
    torch._dynamo.reset()
    counters.clear()
    steps_fn = compiled(memory_steps, CPU, "a chunk of time steps of BPTT")
    p = predictor("lstm")
    graphs = None
    for T in (11, 51, 201):
        args = batch_args(p, T, seed=T)
        want = type(p).bptt([p], p.memory_parameters(), *args)
        got = chunked_bptt(steps_fn, [p], p.memory_parameters(), *args)
        for g, w in zip(got, want):
            torch.testing.assert_close(g, w, rtol=1e-9, atol=1e-11)
        if graphs is None:
            graphs = counters["stats"]["unique_graphs"]
            assert graphs >= 1
        assert counters["stats"]["unique_graphs"] == graphs, T  # no new graph for a longer sequence


def test_a_fused_epoch_in_time_chunks_equals_eager(monkeypatch):
    """``PredictorBatch.fuse`` with sequences longer than TIME_CHUNKED_FROM (patched down to 4) trains
    step by step by ``chunked_bptt``: two members of one GRU batch (chapter 5's observation and
    reward predictors), an epoch in steps of 2 sequences, the same parameters as the eager epoch."""
    monkeypatch.setattr(training, "TIME_CHUNKED_FROM", 4)
    y, a, r, lengths = data(2, 5, 9, seed=3)
    kinds = [dict(reward_output="none", seed=30), dict(reward_output="bits", predict_obs=False, seed=40)]
    fused, eager = ([predictor("gru", lr=0.3, batch_size=2, **k) for k in kinds] for _ in range(2))
    before = [[q.detach().clone() for q in e.parameters()] for e in eager]
    batches = [PredictorBatch(members, y, a, [None, r], lengths) for members in (fused, eager)]
    batches[0].fuse(CPU)
    assert batches[0].time_chunk is not None
    order = torch.rand(2, 5, generator=torch.Generator().manual_seed(4)).argsort(1)
    for batch in batches:
        batch.train_epoch([order, order])
    for f, e, start in zip(fused, eager, before):
        for (name, qf), qe in zip(f.named_parameters(), e.parameters()):
            torch.testing.assert_close(qf, qe, rtol=1e-9, atol=1e-11, msg=name)
        assert any(not torch.equal(qe, q0) for qe, q0 in zip(e.parameters(), start))  # the epoch trained
