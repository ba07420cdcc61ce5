"""ferl.analysis.coding against hand computations and direct (loop) re-implementations."""

from itertools import combinations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from ferl.analysis import coding
from ferl.stats import greedy_accuracy


def test_median_firing_rates_hand_example():
    hidden = np.array(
        [
            [[0.1, 0.9], [0.5, 0.2], [0.3, 0.4]],  # class 0: 3 images, H = 2
            [[1.0, 0.0], [0.0, 1.0], [0.6, 0.7]],
        ]
    )
    np.testing.assert_allclose(coding.median_firing_rates(hidden), [[0.3, 0.4], [0.6, 0.7]])


def test_gram_and_distance_hand_example():
    mfr = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    c = 1 / np.sqrt(2)
    gram, dist = coding.gram_distance(mfr)
    np.testing.assert_allclose(gram, [[1, c, 0], [c, 1, c], [0, c, 1]], atol=1e-12)
    np.testing.assert_allclose(dist, [[0, 2 - 2 * c, 2], [2 - 2 * c, 0, 2 - 2 * c], [2, 2 - 2 * c, 0]], atol=1e-12)


def test_distance_is_squared_euclidean_of_normalised_mfr():
    mfr = np.random.default_rng(0).random((7, 20))
    unit = mfr / np.linalg.norm(mfr, axis=1, keepdims=True)
    _, dist = coding.gram_distance(mfr)
    np.testing.assert_allclose(dist, cdist(unit, unit, "sqeuclidean"), atol=1e-12)


def test_silent_class_gives_finite_distance():
    _, dist = coding.gram_distance(np.array([[0.0, 0.0], [1.0, 0.0]]))
    assert np.isfinite(dist).all()


def _four_points_linkage():
    x = np.array([[0.0], [10.0], [0.1], [10.2]])  # pairs (0, 2) and (1, 3)
    return coding.linkage_from_distance(cdist(x, x, "sqeuclidean"))


@pytest.mark.parametrize(
    "i, j, expected", [(0, 2, True), (2, 0, True), (1, 3, True), (0, 1, False), (0, 3, False), (2, 1, False)]
)
def test_pair_forms_cluster_two_obvious_pairs(i, j, expected):
    assert coding.pair_forms_cluster(_four_points_linkage(), i, j) is expected


def test_pair_in_a_cluster_of_three_is_not_its_own_cluster():
    x = np.array([[0.0], [0.1], [0.5], [9.0]])  # 0 and 1 merge first, then 2 joins them
    z = coding.linkage_from_distance(cdist(x, x))
    assert coding.pair_forms_cluster(z, 0, 1)
    assert not coding.pair_forms_cluster(z, 0, 2)
    assert not coding.pair_forms_cluster(z, 1, 2)


def test_linkage_tolerates_round_off_negatives_and_asymmetry():
    d = np.array([[1e-12, 1.0, 4.0], [1.0 + 1e-13, -1e-14, 2.0], [4.0, 2.0, 0.0]])
    z = coding.linkage_from_distance(d)
    assert z.shape == (2, 4)
    assert coding.pair_forms_cluster(z, 0, 1)


def test_same_action_pairs_cw_noise_floor():
    # Fig. 3.9(a): ("1","2"), ("0","3"), ("6","7"), ("8","N") share actions; "4" is the goal.
    classes = ["0", "1", "2", "3", "4", "N", "6", "7", "8"]
    n, e, s, w = range(4)
    optimal = [e, s, s, e, -1, w, n, n, w]
    pairs = coding.same_action_pairs(classes, optimal)
    assert {frozenset((classes[i], classes[j])) for i, j in pairs} == {
        frozenset(p) for p in (("1", "2"), ("0", "3"), ("6", "7"), ("8", "N"))
    }
    assert all(i < j for i, j in pairs)


def test_same_action_pairs_excludes_goal_and_lists_all_pairs_of_a_triple():
    assert coding.same_action_pairs(list("abcde"), [-1, 2, 2, 2, -1]) == [(1, 2), (1, 3), (2, 3)]


def test_mutual_information_zero_for_identical_classes():
    images = np.random.default_rng(1).random((30, 16))
    mi = coding.pairwise_mutual_information([images, images.copy()], bins=4)
    np.testing.assert_allclose(mi, 0.0, atol=1e-12)


def test_mutual_information_separable_pixel_is_ln2():
    rng = np.random.default_rng(2)
    shared = rng.random((10, 3))
    class_a = np.column_stack([np.zeros(10), shared])  # pixel 0 is the class label
    class_b = np.column_stack([np.ones(10), shared])
    mi = coding.pairwise_mutual_information([class_a, class_b], bins=2)
    np.testing.assert_allclose(mi, [[0, np.log(2) / 4], [np.log(2) / 4, 0]], atol=1e-12)
    one_pixel = coding.pairwise_mutual_information([class_a[:, :1], class_b[:, :1]])
    assert one_pixel[0, 1] == pytest.approx(np.log(2))


def _entropy(counts: np.ndarray) -> float:
    p = counts[counts > 0] / counts.sum()
    return float(-(p * np.log(p)).sum())


def _mi_by_loops(images_by_class, bins):
    """I(Z_i; C) = H(Z_i) − Σ_j ½ H(Z_i | c_j), pixel by pixel, averaged."""
    n_classes = len(images_by_class)
    out = np.zeros((n_classes, n_classes))
    for a, b in combinations(range(n_classes), 2):
        values = []
        for i in range(images_by_class[a].shape[1]):
            hist = [np.histogram(images_by_class[k][:, i], bins=bins, range=(0, 1))[0] for k in (a, b)]
            p_a, p_b = (h / h.sum() for h in hist)
            values.append(_entropy(0.5 * p_a + 0.5 * p_b) - 0.5 * _entropy(hist[0]) - 0.5 * _entropy(hist[1]))
        out[a, b] = out[b, a] = np.mean(values)
    return out


@pytest.mark.parametrize("bins", [2, 3, 5])
def test_mutual_information_matches_loop_computation(bins):
    rng = np.random.default_rng(3)
    # Unequal class sizes: the prior is still ½ per class of the pair.
    images = [rng.random((n, 12)) ** k for n, k in ((7, 1), (11, 2), (9, 3))]
    np.testing.assert_allclose(
        coding.pairwise_mutual_information(images, bins=bins), _mi_by_loops(images, bins), atol=1e-12
    )


def test_greedy_accuracy_hand_example():
    counts = np.zeros((1, 2, 3, 2), dtype=np.int64)  # R=1, L=2, C=3 (class 1 = goal), nA=2
    counts[0, 0] = [[8, 2], [5, 5], [1, 9]]
    counts[0, 1] = [[3, 7], [10, 0], [6, 4]]
    optimal = [0, -1, 1]
    expected = [[(8 + 9) / 20, (3 + 4) / 20]]
    np.testing.assert_allclose(greedy_accuracy(counts, optimal), expected)


def test_greedy_accuracy_without_optimal_actions_is_nan():
    assert np.isnan(greedy_accuracy(np.ones((2, 3, 4, 4)), [-1] * 4)).all()


def test_moving_average_matches_convolution():
    x = np.random.default_rng(4).normal(size=(3, 50))
    expected = np.stack([np.convolve(row, np.ones(7) / 7, mode="valid") for row in x])
    np.testing.assert_allclose(coding.moving_average(x, 7), expected, atol=1e-12)
