"""Preprocessors beyond §5.3.2 (§5.4 "Second" and "Fifth"): the Gaussian–binary RBM against
enumeration and quadrature on tiny models, the DBN against its layers built and trained by hand,
caching and training on synthetic data, bad settings, and the digit maze's pixel noise."""

import itertools
import math

import pytest
import torch

from ferl import interfaces
from ferl.config.params import ConfigError, check_node
from ferl.data import MnistSplit
from ferl.envs.digit_tmaze import DigitTMaze
from ferl.preprocessors import gaussian_rbm
from ferl.preprocessors.dbn import LAYER_SEED_STRIDE, DBNPreprocessor
from ferl.preprocessors.gaussian_rbm import GaussianRBMPreprocessor
from ferl.preprocessors.rbm import RBMPreprocessor, statistics
from test_preprocessor import flat, one_thread, params64, random_biases  # noqa: F401 (one_thread: autouse)

V, H = 3, 4
DATA = torch.tensor([[1.0, -0.5, 0.3], [-1.2, 0.8, 0.0], [0.4, 0.4, -1.5]], dtype=torch.float64)


class NoWriter:
    """A TensorBoard writer that keeps nothing."""

    def __getattr__(self, name):
        return lambda *args, **kwargs: None


# ---- the Gaussian–binary RBM on a tiny model ----------------------------------------------------
def hidden_states(n: int) -> torch.Tensor:
    return torch.tensor(list(itertools.product([0.0, 1.0], repeat=n)), dtype=torch.float64)


def tiny_gaussian(**kw) -> GaussianRBMPreprocessor:
    """Two runs of a 3×4 Gaussian–binary RBM with sizeable weights and random biases."""
    return random_biases(GaussianRBMPreprocessor(2, n_visible=V, n_hidden=H, init_std=0.5, seed=1, **kw))


def energy(v, h, W, b_v, b_h) -> torch.Tensor:
    """E(v, h) = Σ (v − b_v)²/2 − vᵀW h − b_hᵀh (Hinton 2010 §13.2, σ = 1) of every v (B, V)
    with every h (S, H), per run: (R, B, S)."""
    quadratic = 0.5 * (v[None] - b_v[:, None]).pow(2).sum(-1)
    return quadratic[..., None] - torch.einsum("bv,rvh,sh->rbs", v, W, h) - (h @ b_h.T).T[:, None]


def log_partition(W, b_v, b_h) -> torch.Tensor:
    """ln Z per run: ∫ dv exp(−E) = (2π)^{V/2} exp(b_vᵀW h + |W h|²/2) for each h, summed over h."""
    hs = hidden_states(W.shape[2])
    Wh = torch.einsum("rvh,sh->rsv", W, hs)
    terms = (hs @ b_h.T).T + torch.einsum("rv,rsv->rs", b_v, Wh) + 0.5 * Wh.pow(2).sum(-1)
    return 0.5 * W.shape[1] * math.log(2 * math.pi) + torch.logsumexp(terms, -1)


def test_free_energy_is_minus_log_sum_over_hidden_states():
    W, b_v, b_h = params64(tiny_gaussian())
    neg_energy = -energy(DATA, hidden_states(H), W, b_v, b_h)
    torch.testing.assert_close(gaussian_rbm.free_energy(DATA, W, b_v, b_h), -torch.logsumexp(neg_energy, -1))


def test_hidden_expectations_match_enumeration_of_p_h_given_v():
    model = tiny_gaussian()
    raw = torch.rand(5, V, generator=torch.Generator().manual_seed(3))
    model.fit_standardisation(torch.rand(50, V, generator=torch.Generator().manual_seed(4)) * 3)
    v_std = ((raw - model.shift) / model.scale).double()  # the standardisation by hand
    p = torch.softmax(-energy(v_std, hidden_states(H), *params64(model)), -1)  # p(h | v) (R, B, S)
    torch.testing.assert_close(model.transform(raw).double(), p @ hidden_states(H), rtol=1e-5, atol=1e-6)


def test_partition_function_matches_quadrature():
    """The closed form of ln Z used below, against a grid sum of exp(−F(v)) on a 2-visible model."""
    model = GaussianRBMPreprocessor(2, n_visible=2, n_hidden=3, init_std=0.7, seed=2)
    W, b_v, b_h = params64(model)
    step = 0.02
    axis = torch.arange(-12, 12, step, dtype=torch.float64)
    grid = torch.cartesian_prod(axis, axis)
    numeric = torch.logsumexp(-gaussian_rbm.free_energy(grid, W, b_v, b_h), -1) + 2 * math.log(step)
    torch.testing.assert_close(numeric, log_partition(W, b_v, b_h))


def exact_gradient(model, data) -> torch.Tensor:
    """∂/∂θ of the mean log-likelihood −F(v) − ln Z over data, by autograd, per run (R, ·)."""
    W, b_v, b_h = (p.clone().requires_grad_() for p in params64(model))
    log_lik = (-gaussian_rbm.free_energy(data, W, b_v, b_h) - log_partition(W, b_v, b_h)[:, None]).mean(1).sum()
    return flat(torch.autograd.grad(log_lik, (W, b_v, b_h)))


def test_data_term_is_the_gradient_of_minus_free_energy():
    """⟨v ĥᵀ⟩ and ⟨ĥ⟩ of the CD statistics are ∂(−F)/∂W and ∂(−F)/∂b_h on the data; for b_v,
    ∂(−F)/∂b_v = v − b_v: the statistics' ⟨v⟩ is it plus b_v, which cancels in data − model."""
    model = tiny_gaussian()
    v = DATA.float().expand(2, -1, -1)
    _, h_data = model.contrast(v, [torch.Generator().manual_seed(0)] * 2)
    data = statistics(v.double(), h_data.double())
    W, b_v, b_h = (p.clone().requires_grad_() for p in params64(model))
    minus_f = -gaussian_rbm.free_energy(DATA, W, b_v, b_h).mean(1).sum()
    dW, db_v, db_h = torch.autograd.grad(minus_f, (W, b_v, b_h))
    torch.testing.assert_close(data.W, dW, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(data.b_h, db_h, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(data.b_v, db_v + b_v.detach(), rtol=1e-5, atol=1e-6)


def cd_estimate(model, n_samples=30_000, seed=0) -> torch.Tensor:
    v = DATA.float().repeat(n_samples // len(DATA), 1)
    return flat(model.cd_gradient(v, torch.Generator().manual_seed(seed)))


def test_sampled_cd_k_approaches_the_exact_gradient():
    """With v ~ N(W h + b_v, I) in the chain, CD-50 is the exact gradient up to sampling noise;
    CD-1 is biased well beyond it."""
    model = tiny_gaussian(visible="sampled")
    exact = exact_gradient(model, DATA)
    model.cd_k = 50
    error_50 = (cd_estimate(model) - exact).norm(dim=1)
    model.cd_k = 1
    error_1 = (cd_estimate(model) - exact).norm(dim=1)
    assert (error_50 < 0.05 * exact.norm(dim=1)).all(), (error_50, exact.norm(dim=1))
    assert (error_1 > 3 * error_50).all(), (error_1, error_50)


def test_reconstructions_are_the_noise_free_mean_unless_sampled():
    mean, sampled = tiny_gaussian(), tiny_gaussian(visible="sampled")
    h = torch.rand(2, 6, H, generator=torch.Generator().manual_seed(0))
    by_hand = torch.einsum("rvh,rbh->rbv", mean.W, h) + mean.b_v[:, None]
    gens = [torch.Generator().manual_seed(1)] * 2
    torch.testing.assert_close(mean.visible_given(h, gens), by_hand)
    noise = sampled.visible_given(h.repeat(1, 2000, 1), gens) - by_hand.repeat(1, 2000, 1)
    assert abs(noise.mean().item()) < 0.01 and abs(noise.std().item() - 1) < 0.01


def test_standardisation_zero_mean_unit_variance_and_floor():
    images = torch.rand(200, 5, generator=torch.Generator().manual_seed(0)) * torch.tensor([1.0, 2.0, 0.5, 0.0, 0.01])
    model = GaussianRBMPreprocessor(1, n_visible=5, n_hidden=2, min_std=0.1)
    model.fit_standardisation(images)
    std = model.standardise(images)
    torch.testing.assert_close(std.mean(0), torch.zeros(5), atol=1e-5, rtol=0)
    torch.testing.assert_close(std[:, :3].std(0, correction=0), torch.ones(3))
    assert (std[:, 3] == 0).all()  # a constant pixel: centred, scale min_std
    torch.testing.assert_close(model.scale[3:], torch.tensor([0.1, 0.1]))
    # the observations the agent sees: σ(Wᵀ((y − mean)/s) + b_h), s = max(s.d., min_std)
    y = torch.rand(4, 5, generator=torch.Generator().manual_seed(1))
    s = images.std(0, correction=0).clamp(min=0.1)
    by_hand = torch.sigmoid(((y - images.mean(0)) / s) @ model.W[0] + model.b_h[0])
    torch.testing.assert_close(model.transform(y)[0], by_hand)


# ---- training and caching on synthetic data -----------------------------------------------------
def prototypes_split(n_pixels=20, n_train=400, n_test=100, flip=0.05, seed=0) -> MnistSplit:
    """Four random binary prototypes, each pixel flipped with probability ``flip``."""
    g = torch.Generator().manual_seed(seed)
    protos = (torch.rand(4, n_pixels, generator=g) < 0.5).float()

    def draw(n):
        labels = torch.randint(4, (n,), generator=g)
        flips = (torch.rand(n, n_pixels, generator=g) < flip).float()
        return (protos[labels] - flips).abs(), labels

    return MnistSplit(*draw(n_train), *draw(n_test))


def test_gaussian_fit_lowers_held_out_error_and_caches(tmp_path, monkeypatch):
    data = prototypes_split()
    settings = dict(n_visible=20, n_hidden=6, sweeps=15, batch_size=20, cache_dir=str(tmp_path))
    first = GaussianRBMPreprocessor(2, **settings)
    records = first.fit(data, NoWriter())
    assert records["reconstruction_error"].shape == (2, 15) and not records["cached"]
    assert (records["test_error_after"] < 0.5 * records["test_error_before"]).all(), records
    monkeypatch.setattr(RBMPreprocessor, "train", lambda *a, **k: pytest.fail("trained although cached"))
    second = GaussianRBMPreprocessor(2, **settings)
    again = second.fit(data, NoWriter())
    assert again["cached"] and (again["reconstruction_error"] == records["reconstruction_error"]).all()
    torch.testing.assert_close(second.state_dict(), first.state_dict(), rtol=0, atol=0)  # shift and scale too
    assert len(list(tmp_path.glob("gaussianrbmpreprocessor-*.pt"))) == 1


# ---- the DBN ------------------------------------------------------------------------------------
DBN_SETTINGS = dict(sweeps=4, batch_size=20, cd_k=1)


def test_transform_composes_the_layers_by_hand():
    dbn = DBNPreprocessor(2, layers=[6, 5, 4, 3], init_std=1.0)
    v = torch.rand(7, 6, generator=torch.Generator().manual_seed(0))
    h = v.expand(2, -1, -1)
    for layer in dbn.rbms:
        h = torch.sigmoid(torch.einsum("rbv,rvh->rbh", h, layer.W) + layer.b_h[:, None])
    y = dbn.transform(v)
    assert y.shape == (2, 7, 3) and (dbn.input_size, dbn.output_size) == (6, 3)
    torch.testing.assert_close(y, h)
    down = y
    for layer in reversed(dbn.rbms):
        down = torch.sigmoid(torch.einsum("rbh,rvh->rbv", down, layer.W) + layer.b_v[:, None])
    torch.testing.assert_close(dbn.reconstruction_error(v), (down - v).pow(2).mean((1, 2)))


def test_layer_two_is_an_rbm_trained_on_layer_one_expectations():
    """Greedy training: layer 1 is the RBM of the same settings on the images; layer 2 the RBM
    on layer 1's hidden expectations (R, N, H_1), with the streams of seed + 2³² + r."""
    images = prototypes_split().train_images
    dbn = DBNPreprocessor(2, layers=[20, 8, 4], seed=5, **DBN_SETTINGS)
    histories, cached = dbn.train_layers(images)
    one = RBMPreprocessor(2, n_visible=20, n_hidden=8, seed=5, **DBN_SETTINGS)
    one.train(images, progress=False)
    two = RBMPreprocessor(2, n_visible=8, n_hidden=4, seed=5 + LAYER_SEED_STRIDE, **DBN_SETTINGS)
    expected_history = two.train(one.transform(images), progress=False)
    for mine, theirs in ((dbn.rbms[0], one), (dbn.rbms[1], two)):
        torch.testing.assert_close(mine.state_dict(), theirs.state_dict(), rtol=0, atol=0)
    assert (histories[1] == expected_history).all() and cached == [False, False]
    # the equality is of trained weights, not of two untouched initialisations
    initial = RBMPreprocessor(2, n_visible=8, n_hidden=4, seed=5 + LAYER_SEED_STRIDE, **DBN_SETTINGS)
    assert (dbn.rbms[1].W - initial.W).abs().max() > 0.01


def test_dbn_fit_lowers_stack_error_records_and_caches(tmp_path, monkeypatch):
    data = prototypes_split()
    settings = dict(layers=[20, 8, 4], sweeps=20, batch_size=20, cache_dir=str(tmp_path))
    first = DBNPreprocessor(2, **settings)
    records = first.fit(data, NoWriter())
    assert records["reconstruction_error"].shape == (2, 40) and list(records["layer_sweeps"]) == [20, 20]
    assert not records["cached"]
    assert (records["test_error_after"] < 0.6 * records["test_error_before"]).all(), records
    assert len(list(tmp_path.glob("rbmpreprocessor-*.pt"))) == 2  # one entry per layer
    monkeypatch.setattr(RBMPreprocessor, "train", lambda *a, **k: pytest.fail("trained although cached"))
    second = DBNPreprocessor(2, **settings)
    again = second.fit(data, NoWriter())
    assert again["cached"] and (again["reconstruction_error"] == records["reconstruction_error"]).all()
    torch.testing.assert_close(second.state_dict(), first.state_dict(), rtol=0, atol=0)


def test_dbn_runs_are_independent_of_n_runs():
    images = prototypes_split().train_images[:100]
    one, three = (DBNPreprocessor(n, layers=[20, 6, 3], seed=2, **DBN_SETTINGS) for n in (1, 3))
    one.train_layers(images)
    three.train_layers(images)
    for a, b in zip(one.state_dict().values(), three.state_dict().values()):
        torch.testing.assert_close(a[0], b[0], rtol=1e-5, atol=1e-6)  # bmm over 1 or 3 runs may round differently


def test_both_meet_the_preprocessor_protocol():
    assert isinstance(GaussianRBMPreprocessor(2, n_visible=16, n_hidden=4), interfaces.Preprocessor)
    assert isinstance(DBNPreprocessor(2, layers=[16, 8, 4]), interfaces.Preprocessor)


@pytest.mark.parametrize("layers", [[784], [], [784, 0, 20], [784, -3]])
def test_layers_that_do_not_chain_name_the_key(layers):
    with pytest.raises(ValueError, match=r"^layers="):
        DBNPreprocessor(1, layers=layers)
    with pytest.raises(ConfigError, match=r"^preprocessor\.layers=.*is not allowed"):
        check_node({"_target_": "ferl.preprocessors.dbn.DBNPreprocessor", "layers": layers}, "preprocessor.")


@pytest.mark.parametrize("key, value", [("cd_k", 0), ("n_visible", 784), ("visible", "gaussian")])
def test_dbn_checks_the_layer_settings(key, value):
    """The settings passed on to every layer are checked as the RBM's; the sizes come from layers."""
    with pytest.raises(ConfigError, match=rf"^preprocessor\.{key}"):
        check_node({"_target_": "ferl.preprocessors.dbn.DBNPreprocessor", key: value}, "preprocessor.")


@pytest.mark.parametrize("key, value", [("visible", "binary"), ("min_std", 0.0), ("lr", 0)])
def test_gaussian_bad_settings_name_the_key(key, value):
    with pytest.raises(ValueError, match=f"^{key}="):
        GaussianRBMPreprocessor(1, **{key: value})


# ---- the digit maze's pixel noise ---------------------------------------------------------------
CLASSES = {"start_0": 0, "start_1": 0, "corridor": 2, "junction_0": 0, "junction_1": 1, "goal_left": 3, "goal_right": 4}


def grey_split(per_class=3) -> MnistSplit:
    labels = torch.arange(10).repeat_interleave(per_class)
    images = torch.rand(len(labels), 784, generator=torch.Generator().manual_seed(0))
    return MnistSplit(images, labels, images.clone(), labels.clone())


def noisy_maze(n_runs=1, generator=None, **kw) -> DigitTMaze:
    return DigitTMaze(
        n_runs,
        generator or torch.Generator().manual_seed(0),
        grey_split(),
        CLASSES,
        binarize_threshold=None,
        matching=True,
        **kw,
    )


def test_emitted_observations_are_the_image_plus_gaussian_noise():
    """Every start shows class 0's single image: over 3 000 runs its pixels have the image's
    values as means and the noise's s.d."""
    env = noisy_maze(3000, pixel_noise_std=0.3, noise_copies=4000)
    seen = env.reset()
    image = grey_split().train_images[0]
    assert env.observation_table.shape == (7 * 4000, 784) and env.describe()["noise_copies"] == 4000
    assert (seen.mean(0) - image).abs().max() < 0.05
    assert (seen.std(0) - 0.3).abs().max() < 0.04
    assert len(torch.unique(seen, dim=0)) > 2000  # copies drawn afresh, not one per episode


def test_noise_is_one_table_per_config_shared_by_a_class():
    env = noisy_maze(pixel_noise_std=0.3, noise_copies=5)
    advanced = torch.Generator().manual_seed(0)
    torch.rand(100, generator=advanced)  # a maze built later in the job: same seed, other state
    again = noisy_maze(generator=advanced, pixel_noise_std=0.3, noise_copies=5)
    torch.testing.assert_close(env.observation_table, again.observation_table, rtol=0, atol=0)
    table = env.observation_table.view(7, 5, 784)
    names = env.observation_names
    assert torch.equal(table[names.index("start_0")], table[names.index("junction_0")])
    assert not torch.equal(table[names.index("start_0")], table[names.index("junction_1")])
    # without noise the table is the clean reservoir, no copies
    assert noisy_maze(noise_copies=5).observation_table.shape == (7, 784)


def test_noise_with_a_binarize_threshold_is_refused():
    with pytest.raises(ValueError, match=r"^pixel_noise_std=0.3 is not allowed: .*binarize_threshold"):
        DigitTMaze(1, torch.Generator(), grey_split(), CLASSES, matching=True, pixel_noise_std=0.3)
