"""Batched over runs = R single runs (issue 5/7): one batched step of every module changes run r's
parameters exactly as a 1-run module holding copies of run r's slices does, given the same
inputs — actor TD error and update (§3.2, Eq. 3.10), Elman predictor forward / online step /
pattern-mode BPTT epoch (Eqs. 4.1–4.6), RBM preprocessor CD-k gradient and SGD (§5.2) with
aligned per-run random streams.  Every test also checks that the runs' results differ from each
other, so a batched step that mixed runs up (or broadcast one run to all) would fail it.

The NumPy T-maze speed reference (benchmarks/numpy_tmaze_reference.py) is checked against the
torch modules here too: environment, predictor step, BPTT gradients and epoch, one SARSA step.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ferl.actors.free_energy import FERLActor
from ferl.actors.td import td_step
from ferl.envs.tmaze import TMaze, maze_tables
from ferl.predictors.elman import ElmanPredictor
from ferl.preprocessors.rbm import RBMPreprocessor, statistics
from ferl.schedules import Constant

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "numpy_tmaze_reference.py"
_spec = importlib.util.spec_from_file_location("ferl_benchmarks_numpy_tmaze_reference", _PATH)
ref = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = ref
_spec.loader.exec_module(ref)

R = 4
DTYPES = [torch.float64, torch.float32]
TOL = {torch.float64: dict(rtol=1e-10, atol=1e-12), torch.float32: dict(rtol=1e-5, atol=1e-6)}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small matrices: a second intra-op thread only contends on the 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def run_slice(module: torch.nn.Module, r: int, run_keys) -> dict:
    """Module state with the run-batched entries cut to run r (shape (1, …)); others as they are."""
    return {k: (v[r : r + 1].clone() if k in run_keys else v.clone()) for k, v in module.state_dict().items()}


def single_copy(make_single, module, r: int, run_keys):
    one = make_single()
    one.load_state_dict(run_slice(module, r, run_keys))
    return one


def assert_runs_match(batched: dict, singles: list, dtype, what=""):
    """batched[name] (R, …) against singles[r][name] (1, …), and the runs must be distinguishable:
    run r's result is far from every other run's, so a mix-up of runs could not pass."""
    for name, b in batched.items():
        for r, single in enumerate(singles):
            torch.testing.assert_close(b[r], single[name][0], **TOL[dtype], msg=f"{what}{name}, run {r}")
        flat = b.reshape(b.shape[0], -1).double()
        for r in range(len(singles)):
            for q in range(r + 1, len(singles)):
                assert not torch.allclose(flat[r], flat[q], rtol=1e-3, atol=1e-6), (
                    f"{what}{name}: runs {r} and {q} agree, so the test could not see them mixed"
                )


def changes(after: dict, before: dict) -> dict:
    return {k: after[k] - before[k] for k in after}


# ----------------------------------------------------------------------------
# FERL actor
# ----------------------------------------------------------------------------

ACTOR_KEYS = ("W_sh", "W_ah", "b_s", "b_a", "b_h")
S_NODES, HID = 6, 5


def actors(code: str, dtype, n_actions: int, td_rule="sarsa"):
    """An R-run actor with random weights and biases, and a maker of 1-run actors."""
    kw = dict(
        n_state=S_NODES,
        n_actions=n_actions,
        n_hidden=HID,
        td_rule=td_rule,
        gamma=0.9,
        lr=Constant(0.1),
        beta=Constant(1.0),
        action_code=code,
        init_std=0.7,
    )
    batched = FERLActor(n_runs=R, seed=3, **kw).to(dtype)
    g = torch.Generator().manual_seed(11)
    for name in ("b_s", "b_a", "b_h"):
        buf = getattr(batched, name)
        buf.copy_(0.5 * torch.randn(buf.shape, generator=g, dtype=torch.float64))
    return batched, lambda: FERLActor(n_runs=1, seed=99, **kw).to(dtype)


def actor_params(actor) -> dict:
    return {k: getattr(actor, k).clone() for k in ACTOR_KEYS}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("code, n_actions", [("onehot", 4), ("binary", 5)])
def test_actor_update_equals_single_run_updates(code, n_actions, B, dtype):
    """FERLActor.update over R runs (online B = 1 path and batched B > 1 path, with repeated
    actions within a run) = R 1-run actors holding run r's parameters, fed run r's s, a, x, δ."""
    batched, make_single = actors(code, dtype, n_actions)
    g = torch.Generator().manual_seed(5)
    s = torch.rand(R, B, S_NODES, generator=g, dtype=torch.float64).to(dtype)
    a = torch.randint(n_actions, (R, B), generator=g)
    if B > 1:
        a[:, 1] = a[:, 0]  # the same action twice in a run: index_add must accumulate
    delta = torch.randn(R, B, generator=g, dtype=torch.float64).to(dtype)
    lr = 0.07
    singles = [single_copy(make_single, batched, r, ACTOR_KEYS) for r in range(R)]

    F_all, x = batched.evaluate(s)
    x_sa = x.gather(2, a[..., None, None].expand(-1, -1, 1, HID)).squeeze(2)
    before = actor_params(batched)
    batched.update(s, a, x_sa, delta, lr)
    single_changes = []
    for r, one in enumerate(singles):
        F_r, x_r = one.evaluate(s[r : r + 1])
        torch.testing.assert_close(F_all[r : r + 1], F_r, **TOL[dtype])
        torch.testing.assert_close(x[r : r + 1], x_r, **TOL[dtype])
        start = actor_params(one)
        one.update(s[r : r + 1], a[r : r + 1], x_sa[r : r + 1], delta[r : r + 1], lr)
        single_changes.append(changes(actor_params(one), start))
    assert_runs_match(changes(actor_params(batched), before), single_changes, dtype, "Δ")
    assert_runs_match(actor_params(batched), [actor_params(one) for one in singles], dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("rule", ["sarsa", "q", "expected_sarsa"])
def test_actor_sarsa_step_equals_single_run_steps(rule, dtype):
    """A whole online step as the trainers take it (``td_step``: act with pre-drawn uniforms, TD
    error with terminal masks, update) over R runs = the same step of R 1-run actors."""
    batched, make_single = actors("onehot", dtype, 4, td_rule=rule)
    singles = [single_copy(make_single, batched, r, ACTOR_KEYS) for r in range(R)]
    g = torch.Generator().manual_seed(8)
    s, s_next = (torch.rand(R, 1, S_NODES, generator=g, dtype=torch.float64).to(dtype) for _ in range(2))
    u, u_next = (torch.rand(R, 1, 1, generator=g, dtype=torch.float64).to(dtype) for _ in range(2))
    reward = torch.randn(R, 1, generator=g, dtype=torch.float64).to(dtype)
    terminal = torch.tensor([[False], [True], [False], [False]])
    beta, lr = 1.3, 0.05

    def step(actor, sl):
        a, F_sa, x_sa, _ = actor.act(s[sl], beta, None, u[sl])
        alive = torch.ones(len(a), 1, dtype=torch.bool)
        a_next, _, _, delta = td_step(
            actor,
            s[sl],
            a,
            F_sa,
            x_sa,
            reward[sl].squeeze(1),
            s_next[sl],
            lr,
            beta,
            None,
            u_next[sl],
            alive,
            terminal[sl],
        )
        return {"a": a, "a_next": a_next, "delta": delta}

    out = step(batched, slice(None))
    outs = [step(one, slice(r, r + 1)) for r, one in enumerate(singles)]
    for key in ("a", "a_next"):
        assert torch.equal(out[key], torch.cat([o[key] for o in outs]))
    assert_runs_match({"delta": out["delta"]}, [{"delta": o["delta"]} for o in outs], dtype)
    assert_runs_match(actor_params(batched), [actor_params(one) for one in singles], dtype)


# ----------------------------------------------------------------------------
# Elman predictor
# ----------------------------------------------------------------------------

Y, A, M, NR = 5, 4, 6, 3
GAINS = dict(c_y=0.7, c_a=1.3, beta_m=0.8, beta_y=1.2, beta_r=0.9, rho_y=1.5, rho_r=2.5, init_std=0.7)
KINDS = [
    dict(reward_output="bits"),
    dict(reward_output="linear", time_average=True),
    dict(reward_output="none"),
    dict(reward_output="linear", predict_obs=False),
]


def predictors(dtype, lr=0.2, **kind):
    kw = dict(n_obs=Y, n_actions=A, n_memory=M, n_reward=NR, lr=lr, **GAINS, **kind)
    batched = ElmanPredictor(R, seed=20, **kw).to(dtype)
    return batched, lambda: ElmanPredictor(1, seed=99, **kw).to(dtype)


def sequences(dtype, reward_output, B=6, T=7, seed=1):
    """Padded random sequences y (R,B,T+1,Y), one-hot a, targets r and lengths 1 … T that differ
    between runs at the same position (so the batched epoch trims padding the singles do not)."""
    g = torch.Generator().manual_seed(seed)
    y = torch.randint(0, 2, (R, B, T + 1, Y), generator=g).to(dtype)
    a = F.one_hot(torch.randint(0, A, (R, B, T), generator=g), A).to(dtype)
    r = (
        torch.randint(0, 2, (R, B, T + 1, NR), generator=g).to(dtype)
        if reward_output == "bits"
        else torch.randn(R, B, T + 1, 1, generator=g, dtype=torch.float64).to(dtype)
    )
    lengths = torch.randint(1, T + 1, (R, B), generator=g)
    return y, a, (None if reward_output == "none" else r), lengths


def predictor_params(p) -> dict:
    return {k: v.detach().clone() for k, v in p.named_parameters()}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", KINDS, ids=lambda k: "-".join(f"{v}" for v in k.values()))
def test_predictor_train_epoch_equals_single_run_epochs(kind, dtype):
    """train_epoch over R runs = train_epoch of R 1-run predictors holding run r's parameters,
    each on run r's sequences in run r's order."""
    batched, make_single = predictors(dtype, **kind)
    keys = set(predictor_params(batched))
    singles = [single_copy(make_single, batched, r, keys) for r in range(R)]
    y, a, r_, lengths = sequences(dtype, kind["reward_output"])
    order = torch.stack([torch.randperm(y.shape[1], generator=torch.Generator().manual_seed(k)) for k in range(R)])
    before = predictor_params(batched)
    batched.train_epoch(y, a, r_, lengths, order)
    single_changes = []
    for r, one in enumerate(singles):
        start = predictor_params(one)
        one.train_epoch(
            y[r : r + 1], a[r : r + 1], r_[r : r + 1] if r_ is not None else None, lengths[r : r + 1], order[r : r + 1]
        )
        single_changes.append(changes(predictor_params(one), start))
    assert_runs_match(changes(predictor_params(batched), before), single_changes, dtype, "Δ")


@pytest.mark.parametrize("dtype", DTYPES)
def test_predictor_forward_and_online_step_equal_single_runs(dtype):
    """initial / step (the actor phase) and forward_sequences / prediction_errors over R runs =
    the same calls of 1-run predictors on run r's inputs."""
    batched, make_single = predictors(dtype, reward_output="bits")
    keys = set(predictor_params(batched))
    singles = [single_copy(make_single, batched, r, keys) for r in range(R)]
    y, a, r_, lengths = sequences(dtype, "bits")
    g = torch.Generator().manual_seed(3)
    y_prev = torch.randint(0, 2, (R, Y), generator=g).to(dtype)
    a_prev = F.one_hot(torch.randint(0, A, (R,), generator=g), A).to(dtype)

    m0 = batched.initial_state()
    y0 = batched.outputs(m0)[0]
    m1 = batched.step(m0, y_prev, a_prev)
    y1, r1 = batched.outputs(m1)
    y_hat, r_hat, m = batched.forward_sequences(y, a, lengths)
    err = batched.prediction_errors(y, a, r_, lengths)
    got = []
    for r, one in enumerate(singles):
        sl = slice(r, r + 1)
        m0_r = one.initial_state()
        y0_r = one.outputs(m0_r)[0]
        m1_r = one.step(m0_r, y_prev[sl], a_prev[sl])
        y1_r, r1_r = one.outputs(m1_r)
        yh_r, rh_r, m_r = one.forward_sequences(y[sl], a[sl], lengths[sl])
        got.append(
            {
                "m0": m0_r,
                "y0": y0_r,
                "m1": m1_r,
                "y1": y1_r,
                "r1": r1_r,
                "y_hat": yh_r,
                "r_hat": rh_r,
                "m": m_r,
                "err": torch.nan_to_num(one.prediction_errors(y[sl], a[sl], r_[sl], lengths[sl]), -1.0),
            }
        )
    assert_runs_match(
        {
            "m0": m0,
            "y0": y0,
            "m1": m1,
            "y1": y1,
            "r1": r1,
            "y_hat": y_hat,
            "r_hat": r_hat,
            "m": m,
            "err": torch.nan_to_num(err, -1.0),
        },
        got,
        dtype,
    )


# ----------------------------------------------------------------------------
# RBM preprocessor
# ----------------------------------------------------------------------------

VIS, HIDDEN = 12, 5
RBM_KEYS = ("W", "b_v", "b_h")


def rbms(dtype, **kw):
    kw = dict(n_visible=VIS, n_hidden=HIDDEN, batch_size=4, sweeps=2, init_std=0.5, initial_momentum_sweeps=1, **kw)
    batched = RBMPreprocessor(R, seed=2, **kw).to(dtype)
    g = torch.Generator().manual_seed(4)
    batched.b_v.copy_(0.3 * torch.randn(R, VIS, generator=g, dtype=torch.float64))
    batched.b_h.copy_(0.3 * torch.randn(R, HIDDEN, generator=g, dtype=torch.float64))
    return batched, lambda: RBMPreprocessor(1, seed=99, **kw).to(dtype)


def streams(seeds):
    return [torch.Generator().manual_seed(s) for s in seeds]


def rbm_params(model) -> dict:
    return {k: getattr(model, k).clone() for k in RBM_KEYS}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(
    "cd_k, persistent, visible", [(1, False, "mean_field"), (3, False, "binary"), (2, True, "binary")]
)
def test_cd_gradient_equals_single_runs(cd_k, persistent, visible, dtype):
    """The CD-k (PCD-k) gradient over R runs, each run drawing its Gibbs samples from its own
    stream, = the gradient of 1-run RBMs holding run r's parameters and drawing from a copy of
    run r's stream; twice in a row, so PCD's persistent chains are compared too."""
    batched, make_single = rbms(dtype, cd_k=cd_k, persistent=persistent, visible=visible)
    singles = [single_copy(make_single, batched, r, RBM_KEYS) for r in range(R)]
    v = torch.rand(R, 6, VIS, generator=torch.Generator().manual_seed(6), dtype=torch.float64).to(dtype)
    gens, single_gens = streams(range(100, 100 + R)), streams(range(100, 100 + R))
    for _ in range(2):
        grad = batched.cd_gradient(v, gens)
        single_grads = [one.cd_gradient(v[r : r + 1], [single_gens[r]])._asdict() for r, one in enumerate(singles)]
        assert_runs_match(grad._asdict(), single_grads, dtype)
        if persistent:
            assert_runs_match({"chains": batched.chains}, [{"chains": one.chains} for one in singles], dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_cd_statistics_and_sgd_step_equal_single_runs(dtype):
    """The deterministic part of a CD update, given the samples: batch statistics ⟨v hᵀ⟩, ⟨v⟩,
    ⟨h⟩ (Eq. 2.31) and the momentum / weight-decay SGD step."""
    batched, make_single = rbms(dtype)
    singles = [single_copy(make_single, batched, r, RBM_KEYS) for r in range(R)]
    g = torch.Generator().manual_seed(9)
    v, v_model = (torch.rand(R, 6, VIS, generator=g, dtype=torch.float64).to(dtype) for _ in range(2))
    h, h_model = (torch.rand(R, 6, HIDDEN, generator=g, dtype=torch.float64).to(dtype) for _ in range(2))
    data, model = statistics(v, h), statistics(v_model, h_model)
    grad = type(data)(*(d - m for d, m in zip(data, model)))
    velocity = [
        0.1 * torch.randn(p.shape, generator=g, dtype=torch.float64).to(dtype) for p in rbm_params(batched).values()
    ]
    single_velocity = [[vel[r : r + 1].clone() for vel in velocity] for r in range(R)]
    before = rbm_params(batched)
    batched.sgd_step(grad, velocity, 0.9)
    single_changes = []
    for r, one in enumerate(singles):
        sl = slice(r, r + 1)
        d_r, m_r = statistics(v[sl], h[sl]), statistics(v_model[sl], h_model[sl])
        grad_r = type(data)(*(d - m for d, m in zip(d_r, m_r)))
        assert_runs_match({k: x[sl] for k, x in grad._asdict().items()}, [grad_r._asdict()], dtype)
        start = rbm_params(one)
        one.sgd_step(grad_r, single_velocity[r], 0.9)
        single_changes.append(changes(rbm_params(one), start))
    assert_runs_match(changes(rbm_params(batched), before), single_changes, dtype, "Δ")


@pytest.mark.parametrize("persistent", [False, True])
def test_rbm_fit_equals_single_run_fits(persistent):
    """Two sweeps of minibatch CD-k (shuffles, Gibbs samples, momentum switch) on per-run images
    over R runs = the same fit of R 1-run RBMs on run r's images with copies of run r's stream
    (float64, so that no Bernoulli draw flips on rounding)."""
    dtype = torch.float64
    batched, make_single = rbms(dtype, cd_k=2, persistent=persistent, visible="binary")
    singles = [single_copy(make_single, batched, r, RBM_KEYS) for r in range(R)]
    images = torch.rand(R, 10, VIS, generator=torch.Generator().manual_seed(12), dtype=dtype)
    errors = batched.train(images, streams(range(50, 50 + R)), progress=False)
    single_errors = [one.train(images[r : r + 1], streams([50 + r]), progress=False) for r, one in enumerate(singles)]
    assert_runs_match(
        {"errors": torch.as_tensor(errors)}, [{"errors": torch.as_tensor(e)} for e in single_errors], torch.float32
    )  # fit returns float32 errors
    assert_runs_match(rbm_params(batched), [rbm_params(one) for one in singles], dtype)


# ----------------------------------------------------------------------------
# the NumPy T-maze speed reference computes what the torch modules compute
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("matching", [False, True])
def test_numpy_tmaze_dynamics_match_env(matching):
    """Every (position, action, signals) of the NumPy reference maze = ferl.envs.tmaze."""
    env = TMaze(1, torch.Generator().manual_seed(0), corridor_length=4, matching=matching)
    nxt, reward = maze_tables(4, 5.0, -1.0, -0.1)
    for position in range(4):
        for action in range(4):
            for right in (False, True):
                q, rew, done = ref.env_step(position, action, right, 4)
                assert (q, done) == (nxt[position, action], q >= 4)
                assert rew == pytest.approx(reward[position, action, int(right)])
    ids = torch.as_tensor(env._observation_ids())
    for position in range(6):
        for s0 in (0, 1):
            for s1 in (0, 1):
                expected = env.observation_table[ids[position, s0, s1]].numpy()
                np.testing.assert_array_equal(ref.observation(position, s0, s1, 4, matching), expected)


def torch_predictor_from(P: dict, hp=ref.JOINT, lr=0.05) -> ElmanPredictor:
    p = ElmanPredictor(
        1, ref.N_OBS, ref.N_ACTIONS, n_memory=P["b_m"].size, n_reward=P["b_r"].size, lr=lr, **hp
    ).double()
    with torch.no_grad():
        for name, q in p.named_parameters():
            q.copy_(torch.from_numpy(P[name])[None])
    return p


def pad(seqs, T_max=10):
    """Sequences → padded torch tensors (1, B, …) as ferl/trainers/episodes.py stores them."""
    B = len(seqs)
    y = torch.zeros(1, B, T_max + 1, ref.N_OBS, dtype=torch.float64)
    a = torch.zeros(1, B, T_max, ref.N_ACTIONS, dtype=torch.float64)
    r = torch.zeros(1, B, T_max + 1, seqs[0][2].shape[1], dtype=torch.float64)
    lengths = torch.zeros(1, B, dtype=torch.long)
    for i, (ys, acts, rs) in enumerate(seqs):
        T = len(acts)
        y[0, i, : T + 1], a[0, i, :T], r[0, i, : T + 1], lengths[0, i] = (
            torch.from_numpy(ys),
            torch.from_numpy(acts),
            torch.from_numpy(rs),
            T,
        )
    return y, a, r, lengths


@pytest.mark.parametrize(
    "hp",
    [
        ref.JOINT,
        {
            **ref.JOINT,
            "time_average": False,
            "beta_m": 0.8,
            "beta_y": 1.3,
            "beta_r": 0.7,
            "c_y": 0.6,
            "c_a": 1.4,
            "rho_y": 1.5,
        },
    ],
    ids=["joint", "gains"],
)
def test_numpy_bptt_matches_torch_autograd_and_train_epoch(hp):
    """The hand-written NumPy BPTT gradient = autograd of ElmanPredictor.loss (one sequence), its
    online step = ElmanPredictor.step, and one NumPy pattern-mode epoch = train_epoch."""
    rng = np.random.default_rng(0)
    P = ref.init_predictor(rng, n_memory=7)
    seqs = ref.random_sequences(6, rng, lengths=range(3, 9))
    p = torch_predictor_from(P, hp)
    y, a, r, lengths = pad(seqs)
    loss = p.loss(y[:, :1], a[:, :1], r[:, :1], lengths[:, :1]).sum()
    grads = dict(zip([n for n, _ in p.named_parameters()], torch.autograd.grad(loss, list(p.parameters()))))
    loss_np, G = ref.bptt(P, *seqs[0], hp)
    assert loss_np == pytest.approx(float(loss.detach()), rel=1e-12)
    for name, g in grads.items():
        np.testing.assert_allclose(G[name], g[0].numpy(), rtol=1e-10, atol=1e-12, err_msg=name)
    m1 = p.step(p.initial_state(), y[:, 0, 0], a[:, 0, 0])
    np.testing.assert_allclose(
        ref.predictor_step(P, ref.predictor_initial(P, hp), seqs[0][0][0], seqs[0][1][0], hp), m1[0].numpy(), rtol=1e-12
    )
    order = rng.permutation(len(seqs))
    ref.bptt_epoch(P, seqs, order, 0.05, hp)
    p.train_epoch(y, a, r, lengths, torch.as_tensor(order)[None])
    for name, q in p.named_parameters():
        np.testing.assert_allclose(P[name], q[0].detach().numpy(), rtol=1e-9, atol=1e-12, err_msg=name)


def reference_actor(n_state: int, **kw) -> FERLActor:
    """One run of the maze actor as the NumPy reference (``ref``) builds it, in float64."""
    sizes = dict(n_runs=1, n_state=n_state, n_actions=ref.N_ACTIONS, n_hidden=20)
    return FERLActor(
        **sizes, td_rule="sarsa", gamma=0.95, lr=Constant(0.05), beta=Constant(1.0), lr_norm="fan_in", **kw
    ).double()


def test_numpy_sarsa_step_matches_ferl_actor():
    """One SARSA(0) step of the NumPy reference (free energies, TD error with and without a
    terminal, Eq. 3.10 update) = FERLActor.evaluate and ``td_step`` on one run."""
    rng = np.random.default_rng(1)
    n_state = ref.N_OBS + 20
    params = ref.init_actor(rng, n_state, 20)
    params[2][:], params[3][:], params[4][:] = (rng.normal(0, 0.5, p.shape) for p in params[2:])
    actor = reference_actor(n_state)
    for name, value in zip(ACTOR_KEYS, params):
        getattr(actor, name).copy_(torch.from_numpy(value)[None])
    s, s_next = rng.random(n_state), rng.random(n_state)
    a, a_next, reward = 2, 1, -0.1
    alpha = actor.learning_rate(0.0)
    assert alpha == pytest.approx(0.05 / np.sqrt(n_state + ref.N_ACTIONS))
    for terminal, u in ((False, 0.1), (True, 0.9)):
        F_np, x_np = ref.free_energy_all_actions(s, *params)
        F_next_np, _ = ref.free_energy_all_actions(s_next, *params)
        st, st_next = torch.from_numpy(s)[None, None], torch.from_numpy(s_next)[None, None]
        F_all, x = actor.evaluate(st)
        F_next, _ = actor.evaluate(st_next)
        np.testing.assert_allclose(F_all[0, 0].numpy(), F_np, rtol=1e-12)
        np.testing.assert_allclose(F_next[0, 0].numpy(), F_next_np, rtol=1e-12)
        a_next, _, _, delta = td_step(
            actor,
            st,
            torch.tensor([[a]]),
            F_all[:, :, a],
            x[:, :, a],
            torch.tensor([reward], dtype=torch.float64),
            st_next,
            alpha,
            1.0,
            None,
            torch.full((1, 1, 1), u, dtype=torch.float64),
            torch.ones(1, 1, dtype=torch.bool),
            torch.tensor([[terminal]]),
        )
        delta_np = ref.td_error(reward, F_np[a], F_next_np[int(a_next)], 0.95, terminal)
        assert float(delta) == pytest.approx(delta_np, rel=1e-12)
        ref.sarsa_update(params, s, a, ref.sigmoid(x_np[a]), delta_np, alpha)
        for name, value in zip(ACTOR_KEYS, params):
            np.testing.assert_allclose(getattr(actor, name)[0].numpy(), value, rtol=1e-12, atol=1e-15, err_msg=name)


@pytest.mark.parametrize("a_next", [1, 2])  # another action than a = 2, and the same
def test_numpy_fresh_pair_is_the_free_energy_after_the_update(a_next):
    """td_fresh in the NumPy reference: fresh_pair(…) = a re-evaluation of (s', a') after
    sarsa_update, and = what FERLActor.learn returns."""
    rng = np.random.default_rng(4)
    n_state = ref.N_OBS + 20
    params = ref.init_actor(rng, n_state, 20)
    actor = reference_actor(n_state, td_fresh=True)
    for name, value in zip(ACTOR_KEYS, params):
        getattr(actor, name).copy_(torch.from_numpy(value)[None])
    s, s_next, a, delta, alpha = rng.random(n_state), rng.random(n_state), 2, -3.0, 0.01
    _, x = ref.free_energy_all_actions(s, *params)
    F_next, x_next = ref.free_energy_all_actions(s_next, *params)
    ref.sarsa_update(params, s, a, ref.sigmoid(x[a]), delta, alpha)
    F_after, x_after = ref.free_energy_all_actions(s_next, *params)
    F_np, x_np = ref.fresh_pair(
        s, a, ref.sigmoid(x[a]), delta, alpha, s_next, a_next, float(F_next[a_next]), x_next[a_next]
    )
    np.testing.assert_allclose(F_np, F_after[a_next], rtol=1e-10)
    np.testing.assert_allclose(x_np, x_after[a_next], rtol=1e-10)
    assert abs(F_after[a_next] - F_next[a_next]) > 1e-3  # the update moved F(s', a')
    t = lambda v: torch.as_tensor(np.asarray(v, dtype=np.float64)).reshape(1, 1, -1)  # noqa: E731
    F_t, x_t = actor.learn(
        t(s),
        torch.tensor([[a]]),
        t(x[a]),
        torch.tensor([[delta]], dtype=torch.float64),
        alpha,
        t(s_next),
        torch.tensor([[a_next]]),
        t(F_next[a_next]).reshape(1, 1),
        t(x_next[a_next]),
    )
    np.testing.assert_allclose(float(F_t), F_np, rtol=1e-10)
    np.testing.assert_allclose(x_t[0, 0].numpy(), x_np, rtol=1e-10)


def test_numpy_actor_phase_runs_and_is_deterministic():
    out1 = ref.run_numpy_tmaze_reference(30, seed=2)
    out2 = ref.run_numpy_tmaze_reference(30, seed=2)
    np.testing.assert_array_equal(out1["discounted_return"], out2["discounted_return"])
    assert out1["agent_steps"] == out1["steps"].sum() and np.all((out1["steps"] >= 3) & (out1["steps"] <= 10))
    assert np.all(np.isfinite(out1["discounted_return"])) and out1["steps_per_s"] > 0
