"""RBM observation preprocessor (§5.3.2): CD-k against the exact gradient of a tiny RBM, training on
embedded MNIST, run independence, caching and config."""

import itertools

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ferl import rbm
from ferl.data import MnistEmbedded
from ferl.preprocessors.cache import load_or_fit
from ferl.preprocessors.rbm import Gradient, RBMPreprocessor

V, H = 4, 3
DATA = torch.tensor([[1, 1, 0, 0], [0, 0, 1, 1], [1, 0, 1, 0]], dtype=torch.float64)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small matrices: a second intra-op thread only contends with the other test worker (the
    project's cpu_threads = 1); with two threads on a busy 2-core machine these tests ran 20× slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def all_states(n: int) -> torch.Tensor:
    return torch.tensor(list(itertools.product([0.0, 1.0], repeat=n)), dtype=torch.float64)


def random_biases(model):
    """The model with biases N(0, 0.5²) drawn from seed 7, in place."""
    g = torch.Generator().manual_seed(7)
    model.b_v.copy_(0.5 * torch.randn(model.b_v.shape, generator=g))
    model.b_h.copy_(0.5 * torch.randn(model.b_h.shape, generator=g))
    return model


def tiny_rbm(**kw) -> RBMPreprocessor:
    """Two runs of a 4×3 binary RBM with large weights and random biases: slow mixing, so the
    bias of CD-1 stands well above the sampling noise."""
    return random_biases(RBMPreprocessor(2, n_visible=V, n_hidden=H, visible="binary", init_std=2.0, seed=1, **kw))


def params64(model):
    return model.W.double(), model.b_v.double(), model.b_h.double()


def exact_gradient(model, data) -> torch.Tensor:
    """⟨·⟩_data − ⟨·⟩_model (Eq. 2.31), the model term from the joint law of all 2^(V+H) states
    (Eq. 2.18), flattened per run (R, V·H + V + H)."""
    W, b_v, b_h = params64(model)
    vs, hs = all_states(V), all_states(H)
    neg_energy = torch.einsum("av,rvh,bh->rab", vs, W, hs) + (vs @ b_v.T).T[:, :, None] + (hs @ b_h.T).T[:, None]
    p = torch.softmax(neg_energy.flatten(1), -1).view_as(neg_energy)  # p(v_a, h_b) per run
    model_term = Gradient(torch.einsum("rab,av,bh->rvh", p, vs, hs), p.sum(2) @ vs, p.sum(1) @ hs)
    h_data = torch.sigmoid(torch.einsum("nv,rvh->rnh", data, W) + b_h[:, None])
    data_term = Gradient(
        torch.einsum("nv,rnh->rvh", data, h_data) / len(data), data.mean(0).expand_as(b_v), h_data.mean(1)
    )
    return flat(Gradient(*(d - m for d, m in zip(data_term, model_term))))


def flat(grad) -> torch.Tensor:
    return torch.cat([g.reshape(g.shape[0], -1).double() for g in grad], 1)


def test_exact_gradient_matches_autograd_of_log_likelihood():
    """The enumeration above equals ∂/∂θ of mean ln p(v) = −F(v) − ln Σ_v' exp(−F(v')) (Eq. 2.27)."""
    model = tiny_rbm()
    W, b_v, b_h = (p.clone().requires_grad_() for p in params64(model))
    log_z = torch.logsumexp(-rbm.free_energy(all_states(V), W, b_v, b_h), dim=-1)  # (R,)
    log_lik = (-rbm.free_energy(DATA, W, b_v, b_h) - log_z[:, None]).mean(1).sum()
    auto = flat(torch.autograd.grad(log_lik, (W, b_v, b_h)))
    torch.testing.assert_close(exact_gradient(model, DATA), auto)


def cd_estimate(model, n_samples=20_000, calls=1, seed=0) -> torch.Tensor:
    """CD estimate averaged over n_samples copies of DATA (one chain each) and over calls."""
    v = DATA.float().repeat(n_samples // len(DATA), 1)
    g = torch.Generator().manual_seed(seed)
    return sum(flat(model.cd_gradient(v, g)) for _ in range(calls)) / calls


def test_cd_k_approaches_exact_gradient_as_k_grows():
    model = tiny_rbm()
    exact = exact_gradient(model, DATA)
    error, cosine = {}, {}
    for k in (1, 3, 50):
        model.cd_k = k
        estimate = cd_estimate(model)
        error[k] = (estimate - exact).norm(dim=1)
        cosine[k] = torch.cosine_similarity(estimate, exact, dim=1)
    assert (cosine[1] > 0.5).all(), cosine
    assert (error[1] > error[3]).all() and (error[3] > error[50]).all(), error
    # CD-1 is biased far beyond the sampling noise; CD-50 is exact up to it (≈ 0.01).
    assert (error[1] > 5 * error[50]).all(), error
    assert (error[50] < 0.03 * exact.norm(dim=1)).all(), (error[50], exact.norm(dim=1))


def test_pcd_after_burn_in_matches_exact_gradient():
    model = tiny_rbm(persistent=True, cd_k=1)
    exact = exact_gradient(model, DATA)
    cd_estimate(model, n_samples=6000, calls=30)  # burn in the persistent chains; parameters stay fixed
    estimate = cd_estimate(model, n_samples=6000, calls=10, seed=1)
    assert ((estimate - exact).norm(dim=1) < 0.03 * exact.norm(dim=1)).all()
    assert model.chains.shape == (2, 6000, H)


@pytest.fixture(scope="module")
def mnist():
    split = MnistEmbedded().load()
    # every other training image (all 10 classes, 500 images); 200 held-out test images
    return split.train_images[::2], split.test_images[::20]


def test_training_lowers_held_out_reconstruction_error(mnist):
    train, test = mnist
    model = RBMPreprocessor(2, sweeps=10, batch_size=50)
    before = model.reconstruction_error(test)
    history = model.train(train, progress=False)
    after = model.reconstruction_error(test)
    mean_image = (train.mean(0) - test).pow(2).mean()  # what the visible biases alone could reach
    print(
        f"held-out reconstruction error: before {before.tolist()}, after {after.tolist()}, mean image {mean_image:.4f}"
    )
    assert history.shape == (2, 10) and (history[:, -1] < history[:, 0]).all()
    assert (after < 0.3 * before).all() and (after < 0.8 * mean_image).all()


def test_runs_are_independent_of_n_runs(mnist):
    """Run 0 of a 1-run batch and of a 3-run batch with the same seed train identically."""
    train = mnist[0][:200]
    one, three = (RBMPreprocessor(n, sweeps=2, batch_size=50, seed=3) for n in (1, 3))
    one.train(train, progress=False)
    three.train(train, progress=False)
    for a, b in zip(one.state_dict().values(), three.state_dict().values()):
        # same samples and order; bmm over 1 or 3 runs may round differently (≈ 1e-7)
        torch.testing.assert_close(a[0], b[0], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(three.W[0], three.W[1])


def test_transform_shape_range_and_shared_input():
    model = RBMPreprocessor(3, n_visible=10, n_hidden=5, init_std=1.0)
    v = torch.rand(7, 10, generator=torch.Generator().manual_seed(0))
    y = model.transform(v)
    assert y.shape == (3, 7, 5) and ((y > 0) & (y < 1)).all()
    torch.testing.assert_close(y, model.transform(v.expand(3, 7, 10)))
    torch.testing.assert_close(model.reconstruction_error(v), model.reconstruction_error(v.expand(3, 7, 10)))
    assert model.reconstruction_error(v).shape == (3,)


def test_binary_hidden_samples_each_row_from_its_expectation():
    """hidden="binary": h = 1 where the run's uniform (its stream, ``rng.BINARY_HIDDEN`` above its
    training seed) falls below ĥ = σ(Wᵀv + b_h) (against NumPy's); the same samples at
    every call, the mean of many copies of one image ĥ within 4 s.e. of the binomial, and the fit's
    cache key and the reconstruction are those of mean-field outputs."""
    import numpy as np

    from ferl import rng

    kw = dict(n_visible=10, n_hidden=5, init_std=1.0, seed=3)
    mean_field, binary = RBMPreprocessor(2, **kw), RBMPreprocessor(2, **kw, hidden="binary")
    v = torch.rand(4000, 10, generator=torch.Generator().manual_seed(0))
    v[2000:] = v[0]  # 2 000 copies of one image
    W, b = binary.W.numpy().astype(np.float64), binary.b_h.numpy().astype(np.float64)
    p = 1 / (1 + np.exp(-(np.einsum("bv,rvh->rbh", v.numpy().astype(np.float64), W) + b[:, None])))
    u = np.stack(
        [torch.rand(4000, 5, generator=rng.generator(s + rng.BINARY_HIDDEN)).numpy() for s in binary.train_seeds]
    )
    h, expected = binary.transform(v), mean_field.transform(v)
    np.testing.assert_allclose(expected.numpy(), p, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(h.numpy(), (u < expected.numpy()).astype(np.float32))
    torch.testing.assert_close(binary.transform(v), h)
    p0 = p[:, 0]  # (R, H)
    mean = h[:, 2000:].double().mean(1).numpy()
    assert (np.abs(mean - p0) <= 4 * np.sqrt(p0 * (1 - p0) / 2000) + 1e-9).all()
    assert binary.hparams == mean_field.hparams
    torch.testing.assert_close(binary.reconstruct(v), mean_field.reconstruct(v))


def test_load_or_fit_caches_by_settings(tmp_path, monkeypatch):
    images = torch.rand(60, 16, generator=torch.Generator().manual_seed(0))
    settings = dict(n_visible=16, n_hidden=4, sweeps=2, batch_size=20)
    first = RBMPreprocessor(2, **settings)
    errors, cached = load_or_fit(first, images, tmp_path)
    assert not cached and errors.shape == (2, 2)

    def no_training(*args, **kwargs):
        raise AssertionError("trained although a cached fit exists")

    with monkeypatch.context() as m:
        m.setattr(RBMPreprocessor, "train", no_training)
        second = RBMPreprocessor(2, **settings)
        errors2, cached2 = load_or_fit(second, images, tmp_path)
    assert cached2 and (errors2 == errors).all()
    torch.testing.assert_close(second.state_dict(), first.state_dict())

    load_or_fit(RBMPreprocessor(2, **{**settings, "cd_k": 1}), images, tmp_path)  # other settings
    load_or_fit(RBMPreprocessor(2, **settings), images[:40], tmp_path)  # other images
    load_or_fit(RBMPreprocessor(2, **settings, cache_dir="elsewhere"), images, tmp_path)  # where: not the key
    assert len(list(tmp_path.glob("rbmpreprocessor-*.pt"))) == 3 and not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize("key, value", [("cd_k", 0), ("visible", "gaussian"), ("momentum", 1.0), ("batch_size", 0)])
def test_bad_settings_name_the_key(key, value):
    with pytest.raises(ValueError, match=f"^{key}="):
        RBMPreprocessor(1, **{key: value})


def test_config_instantiates_section_5_3_2_settings(compose_cfg):
    cfg = OmegaConf.to_container(compose_cfg(["experiment=table5_1_pixel"]).preprocessor, resolve=True)
    model = instantiate(cfg, n_runs=2, seed=0)
    assert isinstance(model, RBMPreprocessor) and model.cache_dir == cfg["cache_dir"]
    assert model.W.shape == (2, 784, 20) and model.cd_k == 3 and model.sweeps == 600
