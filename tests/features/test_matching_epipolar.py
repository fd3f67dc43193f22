"""match_epipolar's flat-index band and gathered Hamming distances give the pairs of the plain blocked search."""

import numpy as np
import pytest

from vslam.features.matching import best_sorted, hamming_pairs, match_epipolar


def _blocked_reference(uv_a, desc_a, uv_b, desc_b, F_ba, tol_b, epipole_b, min_epipole_px, max_dist, ratio):
    """The float32 band in blocks of 128 rows, 2-D nonzero, row-wise Hamming: what match_epipolar computes."""
    tol = np.broadcast_to(np.asarray(tol_b, dtype=np.float64), (len(uv_b),))
    cols = np.arange(len(uv_b))
    far = np.linalg.norm(uv_b - epipole_b, axis=1) >= np.broadcast_to(np.asarray(min_epipole_px, np.float64), (len(uv_b),))
    cols = cols[far]
    lines = np.c_[uv_a, np.ones(len(uv_a))] @ F_ba.T
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12)[:, None]
    la, lc = lines[:, :2].astype(np.float32), lines[:, 2:3].astype(np.float32)
    ub, tb = np.ascontiguousarray(uv_b[cols].T, dtype=np.float32), tol[cols].astype(np.float32)[None, :]
    ias, jcs = [], []
    for s in range(0, len(la), 128):
        dist = la[s:s + 128] @ ub
        dist += lc[s:s + 128]
        np.abs(dist, out=dist)
        i, j = np.nonzero(dist <= tb)
        ias.append(i + s)
        jcs.append(j)
    ia, jb = np.concatenate(ias), cols[np.concatenate(jcs)]
    if len(ia) == 0:
        return np.zeros((0, 2), np.int64)
    return best_sorted(ia, jb, hamming_pairs(desc_a, desc_b, ia, jb), len(uv_b), max_dist, ratio)


@pytest.mark.parametrize("seed,n_a", [(0, 1500), (1, 1409), (2, 257), (3, 129)])
def test_epipolar_matching_equals_the_blocked_search(seed, n_a):
    """Random views; b holds a's true matches on their epipolar lines, some of them right at the band's edge,
    and repeated descriptors; row counts that leave a short last block."""
    rng = np.random.default_rng(seed)
    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    F = np.linalg.inv(K).T @ np.array([[0, -0.9, 0.1], [0.9, 0, -0.3], [-0.1, 0.3, 0]]) @ np.linalg.inv(K)
    F += rng.normal(0, 1e-9, (3, 3))
    uv_a = rng.uniform([0, 0], [1200, 370], (n_a, 2))
    n_b = 1400
    uv_b = rng.uniform([0, 0], [1200, 370], (n_b, 2))
    tol = np.sqrt(3.84) * 1.2 ** rng.integers(0, 8, n_b)
    h = n_a // 2
    lines = np.c_[uv_a[:h], np.ones(h)] @ F.T
    lines /= np.linalg.norm(lines[:, :2], axis=1)[:, None]
    x = rng.uniform(0, 1200, h)
    off = np.where(rng.random(h) < 0.3, tol[:h] * rng.choice([-1, 1], h), rng.uniform(-1, 1, h))  # on the edge
    uv_b[:h] = np.c_[x, -(lines[:, 0] * x + lines[:, 2] + off * np.hypot(lines[:, 0], lines[:, 1])) / lines[:, 1]]
    desc_a = rng.integers(0, 256, (n_a, 32), dtype=np.uint8)
    desc_b = rng.integers(0, 256, (n_b, 32), dtype=np.uint8)
    desc_b[:h] = desc_a[:h] ^ (rng.random((h, 32)) < 0.03).astype(np.uint8)
    desc_b[h:h + 50] = desc_b[:50]  # repeated descriptors: ties
    epipole = np.array([600.0, 180.0])
    args = (uv_a, desc_a, uv_b, desc_b, F, tol, epipole, 10.0 * np.sqrt(1.2 ** rng.integers(0, 8, n_b)))
    for max_dist, ratio in ((50, 0.7), (80, 0.9)):
        want = _blocked_reference(*args, max_dist=max_dist, ratio=ratio)
        assert len(want) > 20
        np.testing.assert_array_equal(match_epipolar(*args, max_dist=max_dist, ratio=ratio), want)


def test_epipolar_matching_without_candidates():
    uv = np.array([[10.0, 10.0], [20.0, 20.0]])
    d = np.zeros((2, 32), np.uint8)
    F = np.array([[0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # horizontal epipolar lines (pure x translation)
    far_b = np.array([[10.0, 300.0], [20.0, 300.0]])
    assert match_epipolar(uv, d, far_b, d, F, 1.0).shape == (0, 2)
