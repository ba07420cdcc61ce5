"""Chapter-5 observation preprocessor: an RBM trained by contrastive divergence (§5.2, §5.3.2).

Algorithm 2 first trains an RBM on MNIST training images (§5.3.2: 784 visible, 20 hidden nodes,
the whole training set swept 600 times with CD-3) and then shows the agent the hidden
expectations ĥ = σ(Wᵀy⁽⁰⁾ + b_h) of every raw observation y⁽⁰⁾ instead of its pixels.

The model (§2.1.5), batched over runs (W (R, V, H), b_v (R, V), b_h (R, H)), at β = 1:

* energy E(v, h) = −vᵀWh − vᵀb_v − hᵀb_h                                    (Eq. 2.18)
* p(h | v) factorises, p(h_k = 1 | v) = σ(Wᵀv + b_h)_k                (Eq. 2.19 and the next)
* by the symmetry of Eq. 2.18, p(v_i = 1 | h) = σ(W h + b_v)_i
* log-likelihood gradient  ∂/∂W ln p = ⟨v hᵀ⟩_data − ⟨v hᵀ⟩_model        (Eqs. 2.26–2.31),
  with ⟨v⟩ and ⟨h⟩ in place of ⟨v hᵀ⟩ for b_v and b_h (Eqs. 2.24–2.25)
* CD-k: the model term is replaced by the state of a k-step alternating Gibbs chain started at
  the data (Eq. 2.32 for k = 1; CD-n in the text after it); PCD (Tieleman 2008, also named in
  §2.1.5) continues persistent chains instead of restarting them at the data.

Free energies and hidden expectations come from ``ferl.rbm``.

Choices the dissertation does not give (defaults follow Hinton 2010, "A practical guide to
training restricted Boltzmann machines", UTML TR 2010-003, cited by section):

* visible units: grey levels in [0, 1] are the data (the mean-field relaxation at the end of
  §2.1.5); reconstructions are the probabilities σ(W h + b_v), not samples (guide §3.2).
  ``visible="binary"`` samples them, which makes the chain a proper binary RBM sampler.
* hidden units: sampled when driven by data or on the way through the chain, probabilities
  in the statistics and at the last update (guide §3.1–3.3).
* SGD on minibatches of 100 (§4: 10 to 100), learning rate 0.1 and weight cost 2·10⁻⁴ as in
  Hinton & Salakhutdinov's 2006 MNIST RBM code (§7, §10: 10⁻⁵ to 10⁻², on the weights only, not
  the biases), momentum 0.5 for the first 5 sweeps then 0.9 (§9), initial weights N(0, 0.01²)
  and zero biases (§8; the guide's data-based visible biases are not used).
* each run draws its shuffles and Gibbs samples from its own stream seeded from seed + r, so run
  r's whole training does not depend on n_runs.
* the reconstruction error is the mean squared error of the one-step mean-field reconstruction
  σ(W σ(Wᵀv + b_h) + b_v) against v (the guide's §5 monitor, without sampling noise).
"""

from collections.abc import Sequence
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ferl import rbm, rng
from ferl.config.params import Momentum, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.images import IMAGE_SIDE, as_images, tile, weight_images
from ferl.interfaces import FitStopped, PreprocessorBase
from ferl.preprocessors.cache import load_or_fit

VisibleMode = Literal["mean_field", "binary"]
HiddenMode = Literal["mean_field", "binary"]
Generators = torch.Generator | Sequence[torch.Generator]


class Gradient(NamedTuple):
    """Log-likelihood ascent direction (or its data / model term), batched over runs."""

    W: torch.Tensor  # (R, V, H)
    b_v: torch.Tensor  # (R, V)
    b_h: torch.Tensor  # (R, H)


def statistics(v: torch.Tensor, h: torch.Tensor) -> Gradient:
    """Batch means ⟨v hᵀ⟩, ⟨v⟩, ⟨h⟩ of v (R, B, V) and h (R, B, H): one term of Eq. (2.31)."""
    return Gradient(torch.bmm(v.mT, h) / v.shape[1], v.mean(1), h.mean(1))


def per_run(generator: Generators, n_runs: int) -> list:
    """One generator per run: the given sequence, or a single stream that every run draws from."""
    gens = [generator] * n_runs if isinstance(generator, torch.Generator) else list(generator)
    if len(gens) != n_runs:
        raise ValueError(f"{len(gens)} generators given for {n_runs} runs")
    return gens


def uniform(shape, gens: list, like: torch.Tensor, draw=torch.rand) -> torch.Tensor:
    """U(0, 1) numbers (R, *shape) (or ``draw``'s, e.g. torch.randn), run r's from gens[r], on like's
    device and dtype."""
    return torch.stack([draw(shape, generator=g, device=like.device, dtype=like.dtype) for g in gens])


def bernoulli(p: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Binary states that are 1 with probability p, given uniforms u of the same shape."""
    return (u < p).to(p.dtype)


def minibatch(images: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows idx (R, B) of shared images (N, V) or of per-run images (R, N, V) → (R, B, V)."""
    if images.dim() == 2:
        return images[idx]
    return images[torch.arange(idx.shape[0], device=idx.device).unsqueeze(1), idx]


class RBMPreprocessor(PreprocessorBase, nn.Module):
    """RBM observation preprocessor (§5.3.2), n_runs independent RBMs trained at once.

    §5.3.2 gives n_visible = 784, n_hidden = 20, cd_k = 3 and sweeps = 600. It gives none of
    the others; their defaults are those of Hinton's practical guide (see the module docstring):
    lr 0.1, momentum 0.5 for the first ``initial_momentum_sweeps`` = 5 sweeps then 0.9, weight
    decay 2·10⁻⁴ (weights only), minibatches of 100, init_std 0.01, mean-field visible units.
    Run r's initial weights and its training stream come from seed + r. ``hidden``: what
    ``transform`` hands on, ĥ or binary samples of h (not part of the fit).
    """

    stoppable_fit = True  # a stop request ends the fit between sweeps (``train``'s ``stop``)
    W: torch.Tensor  # (R, V, H)
    b_v: torch.Tensor  # (R, V)
    b_h: torch.Tensor  # (R, H)
    chains: torch.Tensor | None  # PCD's persistent chains
    visible: str  # VisibleMode here, a subclass's own modes there

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        n_visible: PositiveInt = 784,
        n_hidden: PositiveInt = 20,
        cd_k: PositiveInt = 3,
        persistent: bool = False,
        lr: Positive = 0.1,
        momentum: Momentum = 0.9,
        initial_momentum: Momentum = 0.5,
        initial_momentum_sweeps: NonNegativeInt = 5,
        weight_decay: NonNegative = 2e-4,
        batch_size: PositiveInt = 100,
        sweeps: PositiveInt = 600,
        init_std: NonNegative = 0.01,
        visible: VisibleMode = "mean_field",
        seed: NonNegativeInt = 0,
        cache_dir: str | None = None,
        hidden: HiddenMode = "mean_field",
    ):
        super().__init__()
        # Every constructor argument that the fit depends on: the cache key of load_or_fit (what
        # the fit hands on, ``hidden``, is not one)
        self.hparams = {k: v for k, v in locals().items() if k not in ("self", "__class__", "cache_dir", "hidden")}
        self.hidden = hidden
        self.cache_dir = cache_dir  # where fits are kept (None: never cached)
        self.input_size, self.output_size = n_visible, n_hidden
        self.cd_k, self.persistent, self.visible = cd_k, persistent, visible
        self.lr, self.weight_decay, self.batch_size, self.sweeps = lr, weight_decay, batch_size, sweeps
        self.momentum, self.initial_momentum, self.initial_momentum_sweeps = (
            momentum,
            initial_momentum,
            initial_momentum_sweeps,
        )
        gens = rng.run_generators(seed, n_runs)
        self.register_buffer("W", torch.stack([torch.randn(n_visible, n_hidden, generator=g) for g in gens]) * init_std)
        self.register_buffer("b_v", torch.zeros(n_runs, n_visible))
        self.register_buffer("b_h", torch.zeros(n_runs, n_hidden))
        # Run r trains on a stream seeded from its own generator after the weights were drawn:
        # independent of n_runs, and not a replay of the numbers that drew its weights.
        self.train_seeds = [rng.child_seed(g) for g in gens]
        self.chains = None  # PCD: hidden states (R, C, H) of the persistent chains

    @property
    def n_runs(self) -> int:
        return self.W.shape[0]

    def describe(self) -> dict:
        return {
            "kind": "rbm",
            "n_visible": self.input_size,
            "n_hidden": self.output_size,
            "cd_k": self.cd_k,
            "sweeps": self.sweeps,
            "hidden": self.hidden,
        }

    def run_generators(self) -> list:
        """Run r's training stream (shuffles and Gibbs samples) on the weights' device."""
        return rng.generators(self.train_seeds, self.W.device)

    # ---- the model -----------------------------------------------------------------------------
    @torch.no_grad()
    def expected_hidden(self, v: torch.Tensor) -> torch.Tensor:
        """ĥ = σ(Wᵀv + b_h) = p(h = 1 | v): v (B, V) shared or (R, B, V) → (R, B, H)."""
        return rbm.hidden_expectation(v.to(self.W), self.W, self.b_h)

    @torch.no_grad()
    def transform(self, v: torch.Tensor) -> torch.Tensor:
        """Processed observations (Algorithm 2): ĥ (``expected_hidden``), or with ``hidden="binary"``
        binary states h ~ p(h | v) (Eq. 5.1's "binary processed observation nodes"), one sample per
        row of v and run, from run r's stream ``rng.BINARY_HIDDEN`` (the same samples at every
        call): v (B, V) shared or (R, B, V) → (R, B, H)."""
        h = self.expected_hidden(v)
        if self.hidden == "mean_field":
            return h
        gens = rng.generators([seed + rng.BINARY_HIDDEN for seed in self.train_seeds], h.device)
        return bernoulli(h, uniform(h.shape[1:], gens, h))

    def visible_input(self, h: torch.Tensor) -> torch.Tensor:
        """Total input W h + b_v of every visible unit: h (R, B, H) → (R, B, V)."""
        return torch.baddbmm(self.b_v.unsqueeze(1), h, self.W.mT)

    def visible_given(self, h: torch.Tensor, gens: list | None = None) -> torch.Tensor:
        """p(v = 1 | h) = σ(W h + b_v) for h (R, B, H); sampled from gens when visible="binary"."""
        p = torch.sigmoid(self.visible_input(h))
        if self.visible == "binary" and gens is not None:
            return bernoulli(p, uniform(p.shape[1:], gens, p))
        return p

    @torch.no_grad()
    def reconstruct(self, v: torch.Tensor) -> torch.Tensor:
        """One-step mean-field reconstruction σ(W ĥ + b_v), ĥ = σ(Wᵀv + b_h): v (B, V) or (R, B, V)
        → (R, B, V)."""
        return self.visible_given(self.expected_hidden(v))

    @torch.no_grad()
    def reconstruction_error(self, v: torch.Tensor) -> torch.Tensor:
        """Mean squared error per run (R,) of the reconstruction of v (B, V) or (R, B, V) against v."""
        v = v.to(self.W)
        return (self.reconstruct(v) - v).pow(2).mean((1, 2))

    # ---- contrastive divergence ----------------------------------------------------------------
    def gibbs(self, h: torch.Tensor, gens: list):
        """cd_k alternating Gibbs steps h → v → h from hidden states h (R, B, H).

        Hidden states are sampled on the way; the last update keeps p(h = 1 | v) (guide §3.3).
        Returns the last visible states and hidden probabilities.
        """
        v = self.visible_given(h, gens)
        p = rbm.hidden_expectation(v, self.W, self.b_h)
        for _ in range(self.cd_k - 1):
            h = bernoulli(p, uniform(p.shape[1:], gens, p))
            v = self.visible_given(h, gens)
            p = rbm.hidden_expectation(v, self.W, self.b_h)
        return v, p

    def negative_phase(self, h_data: torch.Tensor, gens: list):
        """The chain's end (v, p(h | v)): started from h sampled given the data (CD) or from the
        persistent chains (PCD, which are first drawn from the data they meet)."""
        start = (
            self.chains
            if self.persistent and self.chains is not None
            else bernoulli(h_data, uniform(h_data.shape[1:], gens, h_data))
        )
        v, p = self.gibbs(start, gens)
        if self.persistent:
            self.chains = bernoulli(p, uniform(p.shape[1:], gens, p))
        return v, p

    def contrast(self, v: torch.Tensor, gens: list):
        """CD-k estimate of the gradient and the data's hidden expectations (R, B, H)."""
        h_data = rbm.hidden_expectation(v, self.W, self.b_h)  # positive phase, Eq. (2.25)
        data, model = statistics(v, h_data), statistics(*self.negative_phase(h_data, gens))
        return Gradient(*(d - m for d, m in zip(data, model))), h_data

    @torch.no_grad()
    def cd_gradient(self, v: torch.Tensor, generator: Generators) -> Gradient:
        """CD-k (PCD-k when persistent) estimate of the batch-mean log-likelihood gradient
        (Eq. 2.31 with the model term of Eq. 2.32) for v (R, B, V), or (B, V) shared by all runs.

        ``generator``: one per run (independent runs) or a single one that all runs share.
        """
        v = v.to(self.W).expand(self.n_runs, *v.shape[-2:])
        return self.contrast(v, per_run(generator, self.n_runs))[0]

    # ---- training ------------------------------------------------------------------------------
    def sgd_step(self, grad: Gradient, velocity: list, momentum: float) -> None:
        """Δθ ← m Δθ + α (∇θ − λ W), θ ← θ + Δθ; the weight cost λ W on weights only (guide §9–10)."""
        grad = grad._replace(W=grad.W - self.weight_decay * self.W)
        for param, g, vel in zip((self.W, self.b_v, self.b_h), grad, velocity):
            param.add_(vel.mul_(momentum).add_(g, alpha=self.lr))

    def sweep(self, images: torch.Tensor, gens: list, velocity: list, momentum: float) -> torch.Tensor:
        """One pass over the images in minibatches, each run in its own random order; returns the
        reconstruction error per run (R,), each minibatch measured just before its update."""
        n, V = images.shape[-2:]
        order = torch.stack([torch.randperm(n, generator=g, device=images.device) for g in gens])
        squared = torch.zeros(self.n_runs, device=images.device)
        for idx in order.split(self.batch_size, dim=1):
            v = minibatch(images, idx)
            grad, h_data = self.contrast(v, gens)
            squared += (self.visible_given(h_data) - v).pow(2).sum((1, 2))
            self.sgd_step(grad, velocity, momentum)
        return squared / (n * V)

    @torch.no_grad()
    def train(  # type: ignore[override]  # the fit, not Module.train(mode): never put in eval mode
        self,
        images: torch.Tensor,
        generator: Generators | None = None,
        writer=None,
        progress: bool = True,
        stop=None,
        resume: dict | None = None,
    ) -> np.ndarray:
        """Train for ``sweeps`` passes over images (N, V) shared by every run, or (R, N, V).

        ``generator``: None = each run's own stream from seed + r (runs independent of n_runs),
        else one generator per run or a single shared one. Returns the reconstruction error per
        run and sweep (R, sweeps); logs it and run 0's filters to a TensorBoard writer if given.
        ``stop``: asked after every sweep but the last; True raises ``FitStopped``, whose state
        passed as ``resume`` (with the weights as they were) continues the fit exactly.
        """
        images = images.to(self.W)
        gens = per_run(self.run_generators() if generator is None else generator, self.n_runs)
        velocity = [torch.zeros_like(p) for p in (self.W, self.b_v, self.b_h)]
        self.chains, start = None, 0
        errors = np.zeros((self.n_runs, self.sweeps), dtype=np.float32)
        if resume is not None:
            start, errors, velocity, self.chains = (
                resume["sweep"],
                resume["errors"],
                resume["velocity"],
                resume["chains"],
            )
            for g, state in zip(gens, resume["generators"]):
                g.set_state(state)
        for s in tqdm(
            range(start, self.sweeps),
            desc="preprocessor",
            unit="sweep",
            disable=not progress,
            mininterval=1.0,
            initial=start,
            total=self.sweeps,
        ):
            momentum = self.initial_momentum if s < self.initial_momentum_sweeps else self.momentum
            errors[:, s] = self.sweep(images, gens, velocity, momentum).cpu().numpy()
            if writer is not None:
                writer.add_scalar("preprocessor/reconstruction_error", float(errors[:, s].mean()), s + 1)
            if stop is not None and s + 1 < self.sweeps and stop():
                raise FitStopped(
                    {
                        "sweep": s + 1,
                        "errors": errors,
                        "velocity": velocity,
                        "chains": self.chains,
                        "generators": [g.get_state() for g in gens],
                    }
                )
        if writer is not None and self.W.shape[1] == IMAGE_SIDE**2:
            writer.add_images("preprocessor/filters", weight_images(self.W), self.sweeps)
        return errors

    @torch.no_grad()
    def fit(self, data, writer, stop=None, resume: dict | None = None) -> dict:
        """Algorithm 2's first phase (§5.3.2): CD-k on the training images of ``data`` (an
        ``MnistSplit``), or the cached fit of the same settings and images (``cache_dir``); logs the
        held-out reconstruction error before and after, and run 0's reconstructions σ(W ĥ + b_v) of
        one test image per digit class (row 2) under the images (row 1). Returns the records: error
        per run and sweep, held-out errors before / after, whether the fit came from the cache.
        ``stop`` / ``resume``: as ``train``'s (the state also keeps the error before training)."""
        test = data.test_images.to(self.W)
        before = self.reconstruction_error(test) if resume is None else resume["before"]
        try:
            # no generator: every run trains on its own stream (seed + r), so the cache key is complete
            history, cached = load_or_fit(
                self, data.train_images.to(self.W), self.cache_dir, writer, stop=stop, resume=resume
            )
        except FitStopped as e:
            e.state["before"] = before
            raise
        if cached:  # the fit's own logging happened in the run that trained it
            log_training(writer, history, self.W)
        return fit_records(writer, data, history, before, self.reconstruction_error(test), cached, self.reconstruct)


def log_training(writer, history: np.ndarray, W: torch.Tensor) -> None:
    """What ``train`` logs as it goes, from its errors (R, sweeps): the mean error per sweep and
    run 0's filters W (R, 784, H)."""
    for sweep, value in enumerate(history.mean(0), 1):
        writer.add_scalar("preprocessor/reconstruction_error", float(value), sweep)
    if W.shape[1] == IMAGE_SIDE**2:
        writer.add_images("preprocessor/filters", weight_images(W), history.shape[1])


def fit_records(
    writer, data, history: np.ndarray, before: torch.Tensor, after: torch.Tensor, cached: bool, reconstruct
) -> dict:
    """The end of a fit: logs the held-out errors before / after (R,) at sweeps 0 and S (history
    (R, S)) and run 0's ``reconstruct`` (images (B, V) → (R, B, V)) of one test image per digit
    class under the images; returns the records of ``preprocessor.npz``."""
    sweeps = history.shape[1]
    writer.add_scalar("preprocessor/test_reconstruction_error", float(before.mean()), 0)
    writer.add_scalar("preprocessor/test_reconstruction_error", float(after.mean()), sweeps)
    test = data.test_images
    if test.shape[1] == IMAGE_SIDE**2:
        labels = data.test_labels.cpu()
        shown = test[[int(torch.nonzero(labels == c)[0]) for c in labels.unique().tolist()][:10]]
        recon = reconstruct(shown)[0]
        writer.add_image(
            "preprocessor/reconstructions", tile(torch.stack([as_images(shown), as_images(recon)])), sweeps
        )
    return {
        "reconstruction_error": history,
        "test_error_before": before.cpu().numpy(),
        "test_error_after": after.cpu().numpy(),
        "cached": np.bool_(cached),
    }
