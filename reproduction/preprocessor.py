"""The RBM observation preprocessor of chapter 5 (§5.2, §5.3.2; Figs. 5.15–5.16) in numbers.

``Preprocessing`` reads ``records/preprocessor.npz`` (docs/records.md) of a run with a preprocessor
(``preprocessor`` in run.json), the observation names of its environment and, where the
environment records them, the digit class of each (``env.digit_classes``): the
environment's observation table (every image of every observation's reservoir) and each
run's RBM hidden expectations of it, the processed observations y. Observations of one digit
class show the same reservoir, so one reservoir per distinct class is kept: the "500
instances" of Fig. 5.15 (5 classes × 100 images). From them come the PCA of the raw and of
the processed images with the silhouette of the digit classes on PC1–3 and their
nearest-centroid accuracy in the full spaces, their
explained-variance spectra, and the RBM's reconstruction error over its training sweeps and
on held-out images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ferl import stats
from ferl.analysis.coding import pca, subsampled_silhouette
from ferl.analysis.io import fmt, write_csv
from ferl.run.jsonio import strict_dumps
from reproduction import tmaze_figures as figs

RAW_FIGURE, PROCESSED_FIGURE = "Fig. 5.15", "Fig. 5.16"
FIRST_PCS = 20  # Fig. 5.15(c): the first 20 of the 784 PCs
VARIANCE_SHARE = 0.9  # the PCs needed for 90 % of the variance: the tail of Fig. 5.15(b)
MAX_SILHOUETTE_POINTS = 2000  # images per silhouette; bounds the O(n²) distances
FIGURE_RUN = 0  # Fig. 5.16 shows one trained RBM


def pcs_for_share(ratio: np.ndarray, share: float = VARIANCE_SHARE) -> int:
    """Fewest leading PCs whose explained-variance ratios add up to ``share``."""
    return int(min(np.searchsorted(np.cumsum(ratio), share - 1e-12) + 1, len(ratio)))


def nearest_centroid_accuracy(x: np.ndarray, labels: np.ndarray) -> float:
    """Share of the points whose nearest class centroid (Euclidean, all dimensions) is their own
    class's, each left out of its own class's centroid. A measure of class separation that does
    not depend on how many principal components hold the variance."""
    x = np.asarray(x, dtype=np.float64)
    classes, index, counts = np.unique(labels, return_inverse=True, return_counts=True)
    centroids = np.stack([x[index == k].mean(axis=0) for k in range(len(classes))])
    d = ((x[:, None, :] - centroids[None]) ** 2).sum(axis=-1)
    # x − its own class's centroid without x = (x − centroid) · n / (n − 1)
    n = counts[index].astype(np.float64)
    own = np.arange(len(x)), index
    d[own] = np.where(n > 1, d[own] * (n / np.maximum(n - 1, 1)) ** 2, np.inf)
    return float((d.argmin(axis=1) == index).mean())


@dataclass
class Preprocessing:
    records: dict[str, np.ndarray]
    ids: np.ndarray  # observation ids of the distinct images, class by class
    labels: np.ndarray  # class index of each
    class_names: list[str]

    @classmethod
    def from_records(cls, records: dict[str, np.ndarray], names: Sequence[str], digit_classes: dict) -> Preprocessing:
        """``names``: the observations in table order (id n·K + k is image k of names[n]);
        ``digit_classes``: name → digit class (env.digit_classes); a name without one is a
        class of its own."""
        n_ids = len(records["raw_observations"])
        if n_ids % len(names):
            raise ValueError(f"preprocessor.npz: {n_ids} observation ids are not {len(names)} reservoirs of one size")
        k = n_ids // len(names)
        first: dict[str, int] = {}  # class → first observation showing it
        for n, name in enumerate(names):
            first.setdefault(str(digit_classes.get(name, name)), n)
        ids = np.concatenate([n * k + np.arange(k) for n in first.values()])
        return cls(records, ids, np.repeat(np.arange(len(first)), k), list(first))

    @property
    def n_runs(self) -> int:
        return self.records["processed_observations"].shape[0]

    @property
    def reservoir_size(self) -> int:
        return len(self.ids) // len(self.class_names)

    @property
    def shape(self) -> tuple[int, int]:
        """(raw, processed) units: 784 pixels → N^y hidden units (Table 5.1)."""
        return (self.records["raw_observations"].shape[1], self.records["processed_observations"].shape[2])

    @cached_property
    def raw(self) -> tuple[np.ndarray, np.ndarray]:
        """Fig. 5.15: scores on PC1–3 and explained-variance ratios of the raw images."""
        return pca(self.records["raw_observations"][self.ids])

    @cached_property
    def processed(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Fig. 5.16, one per run: the same for the processed observations of the images."""
        return [pca(y[self.ids]) for y in self.records["processed_observations"]]

    @cached_property
    def silhouettes(self) -> tuple[float, np.ndarray]:
        """Silhouette of the digit classes on PC1–3: of the raw images, and (R,) of the
        processed ones (Fig. 5.16(a) "the distribution of each digit class is well preserved")."""
        raw = subsampled_silhouette(self.raw[0], self.labels, MAX_SILHOUETTE_POINTS)
        return raw, np.array(
            [subsampled_silhouette(scores, self.labels, MAX_SILHOUETTE_POINTS) for scores, _ in self.processed]
        )

    @cached_property
    def class_accuracy(self) -> tuple[float, np.ndarray]:
        """Nearest-class-centroid accuracy of the digit classes in the full spaces: of the raw
        images, and (R,) of the processed ones (``nearest_centroid_accuracy``)."""
        raw = nearest_centroid_accuracy(self.records["raw_observations"][self.ids], self.labels)
        processed = self.records["processed_observations"][:, self.ids]
        return raw, np.array([nearest_centroid_accuracy(y, self.labels) for y in processed])

    @property
    def processed_ratios(self) -> np.ndarray:
        return np.array([ratio for _, ratio in self.processed])

    @property
    def reconstruction(self) -> np.ndarray:
        """(R, sweeps) reconstruction error while training (CD-k, §5.3.2)."""
        return self.records["reconstruction_error"].astype(np.float64)

    def held_out(self, when: str) -> np.ndarray:
        """(R,) reconstruction error of held-out images "before" / "after" training."""
        return self.records[f"test_error_{when}"].astype(np.float64)

    @property
    def cached(self) -> bool:
        return bool(self.records["cached"])


def describe(pre: Preprocessing) -> str:
    """The report header's line on the preprocessor."""
    n_raw, n_hidden = pre.shape
    return (
        f"{n_raw} → {n_hidden} units, {pre.reconstruction.shape[1]} training sweeps (all layers) "
        f"({'loaded from the cache' if pre.cached else 'trained in this run'}); PCA of "
        f"{len(pre.ids)} distinct images, {len(pre.class_names)} digit classes "
        f"({', '.join(pre.class_names)}) × {pre.reservoir_size}, raw and processed by each "
        f"run's preprocessor; class separation = nearest-class-centroid accuracy (all units) and silhouette on PC1–3"
    )


def write_tables(pre: Preprocessing, out: Path) -> list[str]:
    """Write the numbers behind Figs. 5.15–5.16 and the training curve; return the file names."""
    ratios = pre.processed_ratios
    write_csv(
        out / "preprocessor_explained_variance.csv",
        ["data", "pc", "mean", "sem"],
        [("raw", k + 1, fmt(x), "") for k, x in enumerate(pre.raw[1])]
        + [
            ("processed", k + 1, fmt(m), fmt(s)) for k, (m, s) in enumerate(zip(ratios.mean(axis=0), stats.sem(ratios)))
        ],
    )
    errors = pre.reconstruction
    write_csv(
        out / "preprocessor_reconstruction_error.csv",
        ["sweep", "mean", "sem", *(f"run_{r}" for r in range(pre.n_runs))],
        [
            (k + 1, fmt(m), fmt(s), *map(fmt, errors[:, k]))
            for k, (m, s) in enumerate(zip(errors.mean(axis=0), stats.sem(errors)))
        ],
    )
    raw, processed = pre.silhouettes
    numbers = {
        "classes": pre.class_names,
        "images_per_class": pre.reservoir_size,
        "units": {"raw": pre.shape[0], "processed": pre.shape[1]},
        "class_silhouette_pc1_3": {
            "raw": raw,
            "processed_mean": float(processed.mean()),
            "processed_runs": processed.tolist(),
        },
        "nearest_centroid_accuracy": {
            "raw": pre.class_accuracy[0],
            "processed_mean": float(pre.class_accuracy[1].mean()),
            "processed_runs": pre.class_accuracy[1].tolist(),
        },
        f"pcs_for_{VARIANCE_SHARE * 100:g}pct_variance": {
            "raw": pcs_for_share(pre.raw[1]),
            "processed_runs": [pcs_for_share(r) for r in ratios],
        },
        "held_out_reconstruction_error": {
            when: {"mean": float(pre.held_out(when).mean()), "runs": pre.held_out(when).tolist()}
            for when in ("before", "after")
        },
        "training_reconstruction_error": {
            "first_sweep_mean": float(errors[:, 0].mean()),
            "last_sweep_mean": float(errors[:, -1].mean()),
        },
        "cached": pre.cached,
    }
    (out / "preprocessor.json").write_text(strict_dumps(numbers, indent=2) + "\n")
    return ["preprocessor_explained_variance.csv", "preprocessor_reconstruction_error.csv", "preprocessor.json"]


def make_figures(pre: Preprocessing) -> dict[str, tuple]:
    """name → (Figure, caption): Figs. 5.15, 5.16 and the RBM's training curve."""
    n_raw, n_hidden = pre.shape
    raw_sil, processed_sil = pre.silhouettes
    images = f"{len(pre.ids)} images ({len(pre.class_names)} digit classes × {pre.reservoir_size})"
    scores, ratio = pre.raw
    scores_r, ratio_r = pre.processed[FIGURE_RUN]
    errors = pre.reconstruction
    return {
        "preprocessor_raw_pca": (
            figs.class_pca(
                scores,
                pre.labels,
                pre.class_names,
                f"projection on PC1–3; class silhouette {raw_sil:.2f}",
                [(f"all {n_raw} PCs", ratio), (f"first {FIRST_PCS} PCs", ratio[:FIRST_PCS])],
                f"{RAW_FIGURE}: PCA of all distinct raw observations, {images}",
            ),
            f"{RAW_FIGURE}: the distinct {n_raw}-pixel observations on PC1–3 by digit class, "
            f"and the explained-variance ratio of all {n_raw} and of the first {FIRST_PCS} PCs",
        ),
        "preprocessor_processed_pca": (
            figs.class_pca(
                scores_r,
                pre.labels,
                pre.class_names,
                f"projection on PC1–3; class silhouette {processed_sil[FIGURE_RUN]:.2f}",
                [(f"all {n_hidden} PCs", ratio_r)],
                f"{PROCESSED_FIGURE}: PCA of the processed observations "
                f"({n_raw} → {n_hidden}, RBM of run {FIGURE_RUN}), {images}",
            ),
            f"{PROCESSED_FIGURE}: the same images processed by the RBM of run {FIGURE_RUN} on "
            f"PC1–3 by digit class, and the explained-variance ratio of all {n_hidden} PCs",
        ),
        "preprocessor_reconstruction_error": (
            figs.reconstruction_error(
                errors.mean(axis=0),
                stats.sem(errors),
                pre.n_runs,
                (pre.held_out("before").mean(), pre.held_out("after").mean()),
                f"RBM preprocessor training (§5.3.2), {n_raw} → {n_hidden}",
            ),
            "§5.3.2 (no figure in the dissertation): the RBM's reconstruction error per training "
            "sweep, mean ± s.e.m. over runs; points: held-out images before / after training",
        ),
    }
