"""An RBM with Gaussian visible and binary hidden units for continuous observations (§5.4 "Fifth").

§5.4 proposes to handle continuous data by "a single RBM with Gaussian visible units and binary
hidden units ... pre-trained using raw continuous data" (Nair and Hinton 2008; the Gaussian
units are also named at the end of §2.1.5, Welling et al. 2005); the agent then sees the binary
hidden units' expectations. This module is chapter 5's RBM preprocessor (``ferl.preprocessors.rbm``:
CD-k, minibatches, momentum, weight cost, caching, batched runs) with the visible units changed,
following Hinton (2010), "A practical guide to training restricted Boltzmann machines", §13.2:

* data: each pixel standardised to zero mean and unit variance over the training images, so
  every visible unit's noise variance is σ_i² = 1 (guide §13.2: "it is much easier to first
  normalise each component of the data to have zero mean and unit variance"). The shift and
  scale are buffers fitted on the training images and applied to every observation
  (``transform``). A pixel whose training s.d. is below ``min_std`` (the embedded subset's
  1 000 training images: 169 of the 784 pixels never lit, 344 with s.d. < 0.1) is divided by
  ``min_std`` instead: its unit variance is undefined, or would magnify what the training
  images never showed there (with min_std 10⁻⁶ the held-out error is 10⁷, with 0.1 it is 0.40).
* energy, σ = 1:  E(v, h) = Σ_i (v_i − b_v,i)²/2 − vᵀW h − b_hᵀh        (guide §13.2)
* p(h_j = 1 | v) = σ(Wᵀv + b_h)_j, as in the binary RBM (Eq. 2.19 and the next);
  v | h ~ N(W h + b_v, I)
* free energy  F(v) = −log Σ_h exp(−E(v, h)) = Σ_i (v_i − b_v,i)²/2 − Σ_j softplus((Wᵀv + b_h)_j)
  (the sum over h of Eqs. 2.20–2.22 with the quadratic visible term in place of −vᵀb_v)
* log-likelihood gradient: ⟨v hᵀ⟩_data − ⟨v hᵀ⟩_model for W, ⟨v⟩ and ⟨h⟩ for the biases, the
  binary RBM's statistics (Eq. 2.31): −∂F/∂b_v = v − b_v, and b_v cancels between the two terms.
* reconstructions: the mean W h + b_v, without noise (guide §13.2: "use noise-free
  reconstructions"); ``visible="sampled"`` adds the unit-variance noise, which makes the CD chain a
  proper sampler of the model (CD-k → the exact gradient as k grows).
* learning rate: "one or two orders of magnitude smaller than when using binary visible units"
  (guide §13.2): 0.01, a tenth of the binary RBM's 0.1 (on the embedded subset's 1 000 images,
  784 → 20, 600 sweeps: held-out error 0.404 at 0.01, 0.408 at 0.001, which after 20 sweeps is
  still at 0.53 where 0.01 reaches 0.43).

Reconstruction errors (training curve and held-out) are mean squared errors in standardised
units (a pixel's variance over the training images is 1), the units the model sees.
"""

from typing import Literal

import numpy as np
import torch

from ferl import rbm
from ferl.config.params import Positive, PositiveInt, checked
from ferl.preprocessors.rbm import RBMPreprocessor, uniform

GaussianVisibleMode = Literal["mean", "sampled"]


def free_energy(v: torch.Tensor, W: torch.Tensor, b_v: torch.Tensor, b_h: torch.Tensor) -> torch.Tensor:
    """F(v) = Σ_i (v_i − b_v,i)²/2 − Σ_j softplus((Wᵀv + b_h)_j) of standardised v (R, B, V) or
    shared (B, V) → (R, B); W (R, V, H), b_v (R, V), b_h (R, H)."""
    quadratic = 0.5 * (v - b_v.unsqueeze(1)).pow(2).sum(-1)
    return rbm.free_energy_from_input(-quadratic, rbm.hidden_input(v, W, b_h))


class GaussianRBMPreprocessor(RBMPreprocessor):
    """Gaussian–binary RBM observation preprocessor (§5.4 "Fifth"), n_runs trained at once.

    Every argument but these is the binary RBM's (``RBMPreprocessor``, conf/preprocessor/rbm.yaml),
    with its defaults: ``lr`` 0.01 (guide §13.2, see the module docstring), ``visible`` "mean"
    (noise-free reconstructions) or "sampled" (v ~ N(W h + b_v, I) in the chain), ``min_std`` the
    smallest per-pixel scale of the standardisation.
    """

    shift: torch.Tensor  # (V,)
    scale: torch.Tensor  # (V,)

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        lr: Positive = 0.01,
        visible: GaussianVisibleMode = "mean",
        min_std: Positive = 0.1,
        **rbm_args,
    ):
        super().__init__(n_runs, lr=lr, **rbm_args)
        self.visible, self.min_std = visible, min_std
        self.hparams.update(visible=visible, min_std=min_std)  # the cache key: every setting of the fit
        # standardisation v_std = (v − shift) / scale, per pixel (V,), fitted on the training images
        self.register_buffer("shift", torch.zeros(self.input_size))
        self.register_buffer("scale", torch.ones(self.input_size))

    def describe(self) -> dict:
        return {**super().describe(), "kind": "gaussian_rbm", "visible": self.visible, "min_std": self.min_std}

    # ---- standardisation (guide §13.2) ---------------------------------------------------------
    def fit_standardisation(self, images: torch.Tensor) -> None:
        """Per-pixel mean and s.d. (floored at ``min_std``) of images (N, V) or (R, N, V), over all images."""
        flat = images.to(self.W).reshape(-1, self.input_size)
        self.shift.copy_(flat.mean(0))
        self.scale.copy_(flat.std(0, correction=0).clamp(min=self.min_std))

    def standardise(self, v: torch.Tensor) -> torch.Tensor:
        """(v − shift) / scale, any shape (…, V)."""
        return (v.to(self.W) - self.shift) / self.scale

    # ---- the model -----------------------------------------------------------------------------
    @torch.no_grad()
    def expected_hidden(self, v: torch.Tensor) -> torch.Tensor:
        """ĥ = σ(Wᵀv_std + b_h) of raw observations v (B, V) shared or (R, B, V) → (R, B, H)."""
        return super().expected_hidden(self.standardise(v))

    def visible_given(self, h: torch.Tensor, gens: list | None = None) -> torch.Tensor:
        """E[v | h] = W h + b_v (standardised units) for h (R, B, H); sampled, v ~ N(W h + b_v, I),
        from gens when visible="sampled"."""
        mean = self.visible_input(h)
        if self.visible == "sampled" and gens is not None:
            return mean + uniform(mean.shape[1:], gens, mean, draw=torch.randn)  # N(0, 1) per run
        return mean

    @torch.no_grad()
    def free_energy(self, v: torch.Tensor) -> torch.Tensor:
        """F of raw observations v (B, V) or (R, B, V), standardised first → (R, B)."""
        return free_energy(self.standardise(v), self.W, self.b_v, self.b_h)

    @torch.no_grad()
    def reconstruct(self, v: torch.Tensor) -> torch.Tensor:
        """The noise-free one-step reconstruction W ĥ + b_v in pixel units: (B, V) or (R, B, V) → (R, B, V)."""
        return super().reconstruct(v) * self.scale + self.shift

    @torch.no_grad()
    def reconstruction_error(self, v: torch.Tensor) -> torch.Tensor:
        """Mean squared error per run (R,) of the reconstruction of v in standardised units."""
        return ((self.reconstruct(v) - v.to(self.W)) / self.scale).pow(2).mean((1, 2))

    # ---- training ------------------------------------------------------------------------------
    @torch.no_grad()
    def train(self, images: torch.Tensor, *args, **kwargs) -> np.ndarray:  # type: ignore[override]  # as the base's
        """The binary RBM's training (CD-k, its streams, logging, stop and resume) on the images
        standardised by their own per-pixel statistics (N, V) or (R, N, V); returns the error (R, sweeps)."""
        self.fit_standardisation(images)
        return super().train(self.standardise(images), *args, **kwargs)

    @torch.no_grad()
    def fit(self, data, writer, stop=None, resume: dict | None = None) -> dict:
        """The binary RBM's fit (``RBMPreprocessor.fit``), the standardisation fitted on the
        training images first, so that the held-out error before training is in the same units."""
        self.fit_standardisation(data.train_images)
        return super().fit(data, writer, stop, resume)
