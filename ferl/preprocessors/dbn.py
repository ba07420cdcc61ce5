"""A deep belief network as the observation preprocessor (§5.4 "Second", §4.4).

§4.4 proposes preprocessing by "a pre-trained deep belief network", §5.4 argues that "the
hierarchical organization of DBNs can preserve more information given the fixed reduced
dimensionality than single-layer [RBMs]". The DBN here is Hinton, Osindero & Teh (2006), "A
fast learning algorithm for deep belief nets", trained greedily (their §4): a stack of chapter 5's
RBMs (``ferl.preprocessors.rbm``, the sizes ``layers`` = [V, H_1, …, H_L]), RBM l trained by CD-k
on the hidden expectations ĥ_{l−1} of the training images under the RBMs below it (the data for
l = 1), each with every setting of conf/preprocessor/rbm.yaml (cd_k, sweeps, lr, …), the same
for every layer. Without the generative fine-tuning of their §5 (up-down algorithm): the agent
sees the recognition pass only.

* processed observation: the upward mean-field pass
  ĥ_L = σ(W_Lᵀ … σ(W_1ᵀ v + b_h,1) … + b_h,L)                 (Eq. 3.1c per layer, β = 1)
* held-out reconstruction error: the pass up and the mean-field pass back down the stack,
  v̂ = σ(W_1 … σ(W_L ĥ_L + b_v,L) … + b_v,1), against v: how much of the image the top layer
  keeps (a single-layer DBN's is the RBM's one-step reconstruction error).
* training curve (``reconstruction_error`` records, R × L·sweeps): the layers' own curves one
  after the other, layer 1's sweeps first; each layer's error is against its own input
  (pixels for layer 1, ĥ_{l−1} above), so the curve jumps where a layer starts.
* runs: run r of layer l draws its initial weights and training stream from seed + l·2³² + r
  (layer 1: seed + r, the RBM preprocessor's own streams), so run r does not depend on n_runs
  and no two layers share a stream.
* caching: one ``load_or_fit`` entry per layer, keyed by the layer's settings and its input
  ĥ_{l−1}, which is itself a function of every setting and the images below (a DBN whose first
  layer is an RBM fitted before loads it).
"""

from typing import cast

import numpy as np
import torch
from torch import nn

from ferl.config.params import ArgumentError, NonNegativeInt, PositiveInt, checked
from ferl.interfaces import PreprocessorBase
from ferl.preprocessors.cache import load_or_fit
from ferl.preprocessors.rbm import RBMPreprocessor, fit_records, log_training

LAYER_SEED_STRIDE = 2**32  # layer l's runs: seed + l · this + r (no overlap below 2³² runs)


class DBNPreprocessor(PreprocessorBase, nn.Module):
    """Greedily trained stack of RBMs (Hinton, Osindero & Teh 2006), n_runs stacks at once.

    ``layers``: the sizes [V, H_1, …, H_L], V = the observation size (input_size) and H_L what the
    agent sees (output_size). Every other argument is passed to each layer's ``RBMPreprocessor``
    (cd_k, sweeps, lr, …, with the RBM's defaults), which sets n_visible / n_hidden from ``layers``.
    """

    kwargs_to = (RBMPreprocessor, ("n_visible", "n_hidden"))  # what the config check sees (params.signature)

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        layers: list[int] = (784, 100, 20),  # type: ignore[assignment]  # immutable default
        seed: NonNegativeInt = 0,
        cache_dir: str | None = None,
        **rbm_args,
    ):
        super().__init__()
        self.sizes, self.cache_dir = [int(n) for n in layers], cache_dir
        self.input_size, self.output_size = self.sizes[0], self.sizes[-1]
        self.rbms = nn.ModuleList(
            RBMPreprocessor(n_runs, n_visible=n_in, n_hidden=n_out, seed=seed + layer * LAYER_SEED_STRIDE, **rbm_args)
            for layer, (n_in, n_out) in enumerate(zip(self.sizes, self.sizes[1:]))
        )

    @property
    def stack(self) -> list[RBMPreprocessor]:
        """The RBMs bottom-up: ``rbms`` as what it holds (indexed, iterated, reversed)."""
        return cast(list[RBMPreprocessor], self.rbms)

    @classmethod
    def check_config(cls, args: dict) -> None:
        """The sizes chain: an input and at least one hidden layer, every one of them positive."""
        sizes = list(args["layers"])
        if len(sizes) < 2 or any(n < 1 for n in sizes):
            raise ArgumentError(
                "layers",
                "a list of ≥ 2 positive sizes [input, hidden …] that chain "
                "(input = the observation size, e.g. [784, 100, 20])",
            )

    def describe(self) -> dict:
        first = self.stack[0]
        return {
            "kind": "dbn",
            "layers": self.sizes,
            "n_visible": self.input_size,
            "n_hidden": self.output_size,
            "cd_k": first.cd_k,
            "sweeps": first.sweeps,
        }

    # ---- the model -----------------------------------------------------------------------------
    @torch.no_grad()
    def transform(self, v: torch.Tensor) -> torch.Tensor:
        """ĥ_L, the upward mean-field pass: v (B, V) shared or (R, B, V) → (R, B, H_L)."""
        for layer in self.stack:
            v = layer.transform(v)
        return v

    @torch.no_grad()
    def reconstruct(self, v: torch.Tensor) -> torch.Tensor:
        """Up the stack and back down by mean-field passes: v (B, V) or (R, B, V) → v̂ (R, B, V)."""
        h = self.transform(v)
        for layer in reversed(self.stack):
            h = layer.visible_given(h)
        return h

    @torch.no_grad()
    def reconstruction_error(self, v: torch.Tensor) -> torch.Tensor:
        """Mean squared error per run (R,) of the whole stack's reconstruction of v against v."""
        v = v.to(self.stack[0].W)
        return (self.reconstruct(v) - v).pow(2).mean((1, 2))

    # ---- greedy layer-wise training ------------------------------------------------------------
    @torch.no_grad()
    def train_layers(self, images: torch.Tensor) -> tuple[list, list]:
        """Hinton et al. (2006) §4: RBM l trained (or loaded from ``cache_dir``) on the hidden
        expectations of images (N, V) under the trained RBMs below it, (R, N, H_{l−1}).
        Returns every layer's errors (R, sweeps) and whether each came from the cache."""
        histories, cached = [], []
        x = images.to(self.stack[0].W)
        for layer in self.stack:
            history, hit = load_or_fit(layer, x, self.cache_dir)
            histories.append(history)
            cached.append(hit)
            x = layer.transform(x)
        return histories, cached

    @torch.no_grad()
    def fit(self, data, writer) -> dict:
        """Algorithm 2's first phase with a DBN: greedy training on the training images of ``data``,
        logged as the RBM's fit is (the curve: the layers' one after the other; filters: layer 1's;
        reconstructions: through the whole stack). Returns the records: the concatenated training
        curve (R, L·sweeps), ``layer_sweeps`` (L,) how many of its sweeps each layer has, the
        held-out stack reconstruction errors before / after, whether every layer came from the cache."""
        test = data.test_images
        before = self.reconstruction_error(test)
        histories, cached = self.train_layers(data.train_images)
        history = np.concatenate(histories, axis=1)
        log_training(writer, history, self.stack[0].W)
        records = fit_records(
            writer, data, history, before, self.reconstruction_error(test), all(cached), self.reconstruct
        )
        return {**records, "layer_sweeps": np.array([h.shape[1] for h in histories])}
