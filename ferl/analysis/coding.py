"""Population coding and behaviour statistics (§3.5, §4.3, §5.3).

Pure numpy/scipy: median firing rates (Eq. 3.12), their Gram matrix and the
derived distance D = g1ᵀ + 1gᵀ − 2G (§3.5.3), hierarchical clustering of D,
the pixel–label mutual information behind Fig. 3.12, moving averages, and the
PCA with the silhouette of labelled points on the leading PCs that scores the
separation of T-junction activations (Figs. 4.14–4.19, 5.7–5.13, 5.20–5.25)
and of digit classes (Figs. 5.15–5.16). Summary statistics over runs are
``ferl.stats``'.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from itertools import combinations

import numpy as np
from scipy.cluster.hierarchy import linkage
from scipy.spatial.distance import cdist, squareform
from scipy.special import entr


def median_firing_rates(hidden: np.ndarray) -> np.ndarray:
    """MFR_c of Eq. (3.12): the median over the test images of class c.

    ``hidden`` is (C, n, H), the action-averaged posterior (1/|A|) Σ_a P(h|z, a)
    for each of the n test images z of each class; returns (C, H).
    """
    return np.median(np.asarray(hidden, dtype=np.float64), axis=1)


def gram_distance(mfr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gram matrix of cosine similarities and the distance of §3.5.3.

    G_ij = cos(MFR_i, MFR_j); D = g1ᵀ + 1gᵀ − 2G with g = diag(G), which is the
    squared Euclidean distance between the L2-normalised MFR vectors.
    Returns (G, D), both (C, C).
    """
    mfr = np.asarray(mfr, dtype=np.float64)
    norms = np.linalg.norm(mfr, axis=1, keepdims=True)
    # A silent class (all-zero MFR) has no direction: it gets g_c = 0, not NaN.
    unit = mfr / np.where(norms > 0, norms, 1.0)
    gram = unit @ unit.T
    g = np.diag(gram)
    return gram, g[:, None] + g[None, :] - 2.0 * gram


def linkage_from_distance(distance: np.ndarray, method: str = "average") -> np.ndarray:
    """Hierarchical clustering (scipy linkage matrix) of a square distance matrix.

    The dissertation does not name the linkage rule of Figs. 3.11–3.13; the
    default is average linkage (UPGMA), which uses D as given without assuming
    it is Euclidean.
    """
    d = np.clip(np.asarray(distance, dtype=np.float64), 0.0, None)  # round-off negatives
    d = 0.5 * (d + d.T)
    np.fill_diagonal(d, 0.0)
    return linkage(squareform(d, checks=False), method=method)


def pair_forms_cluster(linkage_matrix: np.ndarray, i: int, j: int) -> bool:
    """True iff leaves i and j are merged directly with each other.

    That is, the smallest cluster of the dendrogram containing both has exactly
    two members — the "pair forms its own cluster" reading of Fig. 3.11.
    """
    merged = np.asarray(linkage_matrix)[:, :2].astype(np.int64)
    return bool(np.any(((merged[:, 0] == i) & (merged[:, 1] == j)) | ((merged[:, 0] == j) & (merged[:, 1] == i))))


def same_action_pairs(classes: Sequence[str], optimal_action: Sequence[int]) -> list[tuple[int, int]]:
    """Index pairs (i < j) of classes sharing an optimal action (Fig. 3.9).

    The goal class (optimal action −1) is excluded; with the CW noise-tile
    floor these are ("1","2"), ("0","3"), ("6","7"), ("8","N").
    """
    actions = np.asarray(optimal_action)
    assert len(classes) == len(actions)
    return [(i, j) for i, j in combinations(range(len(actions)), 2) if actions[i] >= 0 and actions[i] == actions[j]]


def _pixel_histograms(images: np.ndarray, bins: int) -> np.ndarray:
    """(n, P) intensities in [0, 1] → (P, bins) empirical distribution per pixel."""
    x = np.clip(np.asarray(images, dtype=np.float64), 0.0, 1.0)
    idx = np.minimum((x * bins).astype(np.intp), bins - 1)  # intensity 1.0 → top bin
    return np.eye(bins)[idx].mean(axis=0)


def pairwise_mutual_information(images_by_class: Sequence[np.ndarray], bins: int = 2) -> np.ndarray:
    """Average pixel–label mutual information for every pair of classes (Fig. 3.12).

    For classes C = {c1, c2} with equal prior P(C = c_j) = 1/2 and each pixel Z_i,
    I(Z_i; C) = H(Z_i) − Σ_j P(C = c_j) H(Z_i | C = c_j)   (§3.5.3),
    averaged over pixels, in nats. ``images_by_class`` holds one (n_c, P) array
    per class; returns the (C, C) matrix, diagonal 0. Low MI ⇒ perceptually
    similar classes.

    Intensities are discretised into ``bins`` equal-width bins. The default, 2
    (ink vs. background, threshold 0.5), suits MNIST, whose intensities pile up
    at 0 and 1, so two bins keep nearly all the class information; it also keeps
    the plug-in estimator's upward bias, about (bins − 1)/(4n) nats for n
    images per class (≈ 6·10⁻⁴ at n = 400), well below the differences between
    digit pairs, whereas 16 bins would raise it ~15-fold.
    """
    if bins < 2:
        raise ValueError(f"bins must be >= 2, got {bins}")
    p = np.stack([_pixel_histograms(imgs, bins) for imgs in images_by_class])  # (C, P, B)
    h_given_c = entr(p).sum(axis=-1)  # (C, P)
    mixture = 0.5 * (p[:, None] + p[None, :])  # (C, C, P, B)
    mi = entr(mixture).sum(axis=-1) - 0.5 * (h_given_c[:, None] + h_given_c[None, :])
    mi = mi.mean(axis=-1)
    np.fill_diagonal(mi, 0.0)
    return mi


def moving_average(values: np.ndarray, window: int = 100) -> np.ndarray:
    """Mean over the trailing ``window`` entries of the last axis (Fig. 3.4).

    (…, T) → (…, T − window + 1); entry t averages steps t … t + window − 1.
    """
    values = np.asarray(values, dtype=np.float64)
    window = min(window, values.shape[-1])
    csum = np.cumsum(values, axis=-1)
    csum = np.concatenate([np.zeros(values.shape[:-1] + (1,)), csum], axis=-1)
    return (csum[..., window:] - csum[..., :-window]) / window


def nanmean(x: np.ndarray, axis=None) -> np.ndarray:
    """np.nanmean without the warning for cells that are NaN in every run (a prediction error at
    t > T, a silhouette undefined in every run)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(x, axis=axis)


# ---- PCA and the separation of labelled points (§4.3.2, §5.3) ----------------


def silhouette_score(points: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette coefficient (Rousseeuw, 1987) of a labelling, Euclidean distance.

    s_i = (b_i − a_i) / max(a_i, b_i), with a_i the mean distance of point i to the
    other members of its cluster and b_i the smallest mean distance to another
    cluster; s_i = 0 in a singleton cluster or where a_i = b_i = 0. NaN with fewer
    than two labels. Distances below 10⁻⁹ of the points' scale count as 0: points equal up to
    rounding (a converged memory visits a handful of states) are equal, so that their s_i does
    not depend on the last bits of a projection ((b − a) / max(a, b) of two rounding errors).

    Identical (point, label) pairs share one s_i, so the distances are taken between the m distinct
    pairs only, each weighted by its count (m × m instead of n × n: a converged memory's visits are
    a few distinct points). A duplicate of i adds 0 to i's own sum and 1 to its cluster's size.
    """
    x = np.asarray(points, dtype=np.float64)
    classes, idx = np.unique(np.asarray(labels), return_inverse=True)
    if len(classes) < 2:
        return float("nan")
    idx = idx.ravel()
    _, first, weight = np.unique(np.column_stack([x, idx]), axis=0, return_index=True, return_counts=True)
    x, idx = x[first], idx[first]
    member = np.eye(len(classes))[idx] * weight[:, None]  # (m, k) points of each cluster at each pair
    counts = member.sum(axis=0)
    distance = cdist(x, x)
    distance[distance <= 1e-9 * np.abs(x).max(initial=0.0)] = 0.0
    sums = distance @ member  # (m, k) summed distance to each cluster's n_c points
    rows = np.arange(len(x))
    own = counts[idx]
    a = sums[rows, idx] / np.maximum(own - 1, 1)
    to_other = sums / counts
    to_other[rows, idx] = np.inf
    b = to_other.min(axis=1)
    denom = np.maximum(a, b)
    s = np.where((own > 1) & (denom > 0), (b - a) / np.where(denom > 0, denom, 1.0), 0.0)
    return float(weight @ s / weight.sum())


def pca(x: np.ndarray, n_components: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """PCA of the centred data X (n, d): the eigenvectors V of XᵀX (d × d, far cheaper than an
    SVD of X when n ≫ d, as for junction visits); by SVD of X when n < d.

    Returns the scores XV on the first ``n_components`` PCs, (n, n_components), zero where
    there are fewer components (samples or units), each PC's sign chosen so that its largest
    loading is positive; and the explained-variance ratio of every PC, one per unit (zeros
    past the rank).
    """
    x = np.asarray(x, dtype=np.float64)
    x = x - x.mean(axis=0)
    if len(x) >= x.shape[1]:
        variance, v = np.linalg.eigh(x.T @ x)  # ascending
        variance, v = np.clip(variance[::-1], 0.0, None), v[:, ::-1]
    else:
        _, s, vt = np.linalg.svd(x, full_matrices=False)
        variance, v = s**2, vt.T
    k = min(n_components, v.shape[1])
    v = v[:, :k] * np.sign(v[np.abs(v[:, :k]).argmax(axis=0), np.arange(k)])
    scores = np.zeros((len(x), n_components))
    scores[:, :k] = x @ v
    ratio = np.zeros(x.shape[1])
    total = variance.sum()
    if total > 0:
        ratio[: len(variance)] = variance / total
    return scores, ratio


def nonfinite_rows(x: np.ndarray) -> np.ndarray:
    """(n,) True where a row of ``x`` (n, d) holds a NaN or ±inf. A row's sum in float64 is finite
    exactly when all its entries are (no row of finite float16 or float32 values overflows it), and
    is ~8× faster on a float16 record of 10⁵ visits × 804 units than ``~isfinite(x).all(axis=1)``."""
    with np.errstate(invalid="ignore"):  # inf − inf: NaN, as it should be here
        return ~np.isfinite(np.asarray(x).sum(axis=1, dtype=np.float64))


def _subsample(n: int, size: int) -> np.ndarray:
    """The same ``size`` of n indices every time (deterministic, in order)."""
    if n <= size:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, size, replace=False))


def subsampled_silhouette(points: np.ndarray, labels: np.ndarray, max_points: int) -> float:
    """``silhouette_score`` of the same ≤ ``max_points`` points every time (bounds the O(n²)
    distances)."""
    keep = _subsample(len(points), max_points)
    return silhouette_score(np.asarray(points)[keep], np.asarray(labels)[keep])
