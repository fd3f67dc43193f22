"""match_by_projection's flat-index candidate path: the same distances and pairs as the plain forms."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from vslam.features.matching import _best_pairs_binary, best_pairs, hamming_pairs, hamming_rows, match_by_projection


def test_hamming_pairs_equals_the_byte_table():
    rng = np.random.default_rng(0)
    for width in (8, 32, 64):
        a = rng.integers(0, 256, (50, width), dtype=np.uint8)
        b = rng.integers(0, 256, (70, width), dtype=np.uint8)
        ia, jb = rng.integers(0, 50, 400), rng.integers(0, 70, 400)
        got = hamming_pairs(a, b, ia, jb)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, hamming_rows(a[ia], b[jb]))


def _candidates(kp_uv: np.ndarray, pred: np.ndarray, radius: float) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    """The keypoints within ``radius`` of each prediction as ``match_by_projection`` finds them: (tree, valid
    (P,k) bool, ki (P,k) keypoint indices)."""
    tree = cKDTree(kp_uv)
    k = min(16, len(kp_uv))
    d, ki = tree.query(pred, k=k, distance_upper_bound=radius)
    d, ki = d.reshape(len(pred), k), ki.reshape(len(pred), k)
    return tree, np.isfinite(d) & (d <= radius), ki


def test_best_pairs_binary_equals_best_pairs_on_the_tree_grid():
    """Ties included: few distinct descriptors, keypoints on a coarse lattice (equal pixel distances)."""
    rng = np.random.default_rng(1)
    for trial in range(30):
        n, p = int(rng.integers(2, 300)), int(rng.integers(1, 300))
        kp_uv = rng.integers(0, 40, (n, 2)).astype(np.float64)
        palette = rng.integers(0, 256, (int(rng.integers(2, 8)), 32), dtype=np.uint8)
        kp_desc = palette[rng.integers(0, len(palette), n)]
        pt_desc = palette[rng.integers(0, len(palette), p)].copy()
        pt_desc[:, 1] ^= rng.integers(0, 8, p).astype(np.uint8)
        pred = rng.uniform(0, 40, (p, 2))
        radius = float(rng.choice([2.0, 4.0, 9.0]))
        ratio = None if trial % 4 == 0 else 0.9
        tree, valid, ki = _candidates(kp_uv, pred, radius)
        if not valid.any():
            continue
        qi, ti = np.nonzero(valid)[0], ki[valid].astype(np.int64)
        want = best_pairs(qi, ti, hamming_rows(pt_desc[qi], kp_desc[ti]).astype(float), 64, ratio)
        np.testing.assert_array_equal(_best_pairs_binary(valid, ki, pt_desc, kp_desc, 64, ratio), want)
        np.testing.assert_array_equal(match_by_projection(pred, pt_desc, kp_uv, kp_desc, radius, 64, ratio, tree), want)


def test_best_pairs_float_equals_best_pairs_on_the_tree_grid():
    """The float32 path (learned descriptors) gives best_pairs' pairs exactly, ties included: few distinct
    descriptors (equal distances), keypoints on a coarse lattice, the ratio test on and off."""
    from vslam.features.matching import _best_pairs_float, descriptor_rows

    rng = np.random.default_rng(2)
    for trial in range(40):
        n, p = int(rng.integers(2, 300)), int(rng.integers(1, 300))
        kp_uv = rng.integers(0, 40, (n, 2)).astype(np.float64)
        palette = rng.standard_normal((int(rng.integers(2, 8)), 64)).astype(np.float32)
        palette /= np.linalg.norm(palette, axis=1, keepdims=True)
        kp_desc = palette[rng.integers(0, len(palette), n)]
        pt_desc = palette[rng.integers(0, len(palette), p)] + 0.05 * rng.integers(0, 3, (p, 1)).astype(np.float32)
        pred = rng.uniform(0, 40, (p, 2))
        radius = float(rng.choice([2.0, 4.0, 9.0]))
        ratio = None if trial % 4 == 0 else 0.9
        max_dist = float(rng.choice([np.inf, 64.0]))
        tree, valid, ki = _candidates(kp_uv, pred, radius)
        if not valid.any():
            continue
        qi, ti = np.nonzero(valid)[0], ki[valid].astype(np.int64)
        want = best_pairs(qi, ti, descriptor_rows(pt_desc[qi], kp_desc[ti]).astype(float), max_dist, ratio)
        np.testing.assert_array_equal(_best_pairs_float(valid, ki, pt_desc, kp_desc, max_dist, ratio), want)
        got = match_by_projection(pred, pt_desc, kp_uv, kp_desc, radius, max_dist, ratio, tree)
        np.testing.assert_array_equal(got, want)
