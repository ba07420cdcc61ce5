"""What one phase hands to the phases after it, as typed fields rather than string keys.

``PhaseOutputs`` holds what a phase computes for later ones; a checkpoint saves it with the
run's progress, so a resumed run's later phases find it as the earlier phases left it, and it is
emptied once the last phase has finished (a finished run keeps parameters, not data).
``Prepared`` holds what phases draw in ``prepare`` at every start, in a fixed order (not saved:
a resumed run draws it again alike). A new phase that hands something on adds a field here,
named for what it is, with its shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Episodes:
    """Whole episodes per run, padded to T_max: what the random collection of Algorithms 1–2 gives
    the predictors (§4.2) and what replay stores."""

    obs: torch.Tensor  # (R, N, Tmax+1) observation ids y_0 … y_T
    actions: torch.Tensor  # (R, N, Tmax) action indices a_0 … a_{T−1}
    rewards: torch.Tensor  # (R, N, Tmax) rewards r_1 … r_T
    lengths: torch.Tensor  # (R, N) T, number of actions

    def select(self, index: torch.Tensor) -> Episodes:
        """Per-run subset: index (R, n) into the episode axis."""

        def take(x):
            shape = index.shape + x.shape[2:]
            return x.gather(1, index.view(*index.shape, *([1] * (x.dim() - 2))).expand(shape))

        return Episodes(take(self.obs), take(self.actions), take(self.rewards), take(self.lengths))


@dataclass
class SplitEpisodes:
    """Algorithm 1's data (§4.3.1, ``CollectEpisodes``): random-policy episodes balanced over the
    lengths T_min … T_max, split into training and test episodes, ``n_train`` and ``n_test`` of
    each length per run."""

    train: Episodes
    test: Episodes
    n_train: int
    n_test: int


@dataclass
class PhaseOutputs:
    """What the phases of a run hand on (saved with its progress until the run has finished)."""

    observations: torch.Tensor | None = None  # (R, ids, Y) the processed observation table (FitPreprocessor)
    episodes: SplitEpisodes | None = None  # the predictors' data (CollectEpisodes)
    random_steps: np.ndarray | None = None  # (R,) environment steps the random collection cost each run
    floor_test_before: dict | None = None  # the "before" test's responses (GreedyTests), for the records


@dataclass
class Prepared:
    """What phases prepare at every start (drawn again alike when a run resumes, never saved)."""

    floor_test_images: torch.Tensor | None = None  # (C, n, P) clean held-out test images per floor class
    episodes_per_run: int = 0  # random episodes the collection will keep per run
