"""Extractor bucketing and descriptor matching: exact answers on constructed inputs."""

import cv2
import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.features import EXTRACTORS, FeatureConfig, make_extractor
from scipy.spatial import cKDTree

from vslam.features.matching import BITS_PER_L2, best_pairs, descriptor_rows, hamming_rows, match_by_projection, match_epipolar, match_mutual
from vslam.geometry.se3 import inv_T, make_T, skew, so3_exp
from vslam.features.orb import bucket


def _desc(n, rng):
    return rng.integers(0, 256, size=(n, 32), dtype=np.uint8)


def test_hamming_rows():
    a = np.zeros((2, 32), np.uint8)
    b = a.copy()
    b[0, 0] = 0b1011
    b[1, :] = 255
    assert hamming_rows(a, b).tolist() == [3, 256]


def test_mutual_matching_recovers_a_permutation():
    rng = np.random.default_rng(0)
    d1 = _desc(200, rng)
    perm = rng.permutation(200)
    d2 = d1[perm].copy()
    m = match_mutual(d1, d2)
    assert len(m) == 200
    assert np.array_equal(perm[m[:, 1]], m[:, 0])


def test_float_mutual_matching_equals_the_brute_force_definition():
    """Float descriptors (ConvPoint, SIFT: not unit length) from one matrix product: the same pairs as the
    definition evaluated pair by pair (OpenCV's brute force matcher, used before), for each ratio / distance gate;
    ties go to the lower index in both directions."""
    rng = np.random.default_rng(7)
    d2 = rng.standard_normal((300, 128)).astype(np.float32) * rng.uniform(0.5, 2.0, (300, 1)).astype(np.float32)
    d1 = d2[rng.integers(0, 300, 500)] + 0.3 * rng.standard_normal((500, 128)).astype(np.float32)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd, bwd = bf.knnMatch(d1, d2, k=2), {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(d2, d1, k=1)}
    for ratio, max_bits in ((0.8, np.inf), (None, np.inf), (0.95, 300.0)):
        want = [(m[0].queryIdx, m[0].trainIdx) for m in fwd if (ratio is None or m[0].distance < ratio * m[1].distance)
                and m[0].distance * BITS_PER_L2 <= max_bits and bwd[m[0].trainIdx] == m[0].queryIdx]
        got = match_mutual(d1, d2, ratio=ratio, max_dist=max_bits)
        assert 0 < len(got) and got.tolist() == [list(p) for p in want]
    same = np.ones((3, 4), np.float32)  # all distances tie: row 0 <-> column 0 only, no ratio test passes
    assert match_mutual(same, same, ratio=None).tolist() == [[0, 0]]
    assert len(match_mutual(same, same, ratio=0.99)) == 0


def _bf_mutual(d1, d2, ratio, max_dist):
    """match_mutual's binary pairs as OpenCV's brute-force matcher gives them (two k-NN passes)."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    bwd = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(d2, d1, k=1)}
    return [[m[0].queryIdx, m[0].trainIdx] for m in bf.knnMatch(d1, d2, k=2)
            if (ratio is None or m[0].distance < ratio * m[1].distance) and m[0].distance <= max_dist
            and bwd[m[0].trainIdx] == m[0].queryIdx]


@pytest.mark.parametrize("seed", [0, 1])
def test_binary_mutual_matching_equals_opencvs_brute_force(seed):
    """The one-matrix popcount path gives OpenCV's pairs, ties included (lower index wins both ways): noisy copies
    of 700 descriptors among 1300 (two blocks of rows and a partial one), and 2-bit descriptors where nearly every
    distance ties."""
    rng = np.random.default_rng(seed)
    d2 = _desc(1300, rng)
    d1 = np.vstack([_flip_bits(d2[rng.permutation(1300)[:700]], 20, rng), _desc(600, rng)])
    coarse = rng.integers(0, 2, (300, 32), dtype=np.uint8)
    for a, b in ((d1, d2), (coarse, coarse[::-1].copy()), (coarse[:40], coarse[10:]), (d1[:2], d2[:3])):
        for ratio, max_dist in ((0.8, np.inf), (None, np.inf), (0.9, 60), (0.99, 0)):
            want = _bf_mutual(a, b, ratio, max_dist)
            got = match_mutual(a, b, ratio=ratio, max_dist=max_dist)
            assert got.dtype == np.int64 and got.tolist() == want
    assert len(match_mutual(d1, d2, ratio=0.8)) > 600


def test_projection_matching_radius_threshold_and_uniqueness():
    rng = np.random.default_rng(1)
    kp_desc = _desc(50, rng)
    kp_uv = rng.uniform(0, 300, size=(50, 2))
    # points 0..9 predicted 1 px from keypoints 0..9 with their descriptors
    pred = kp_uv[:10] + 1.0
    pairs = match_by_projection(pred, kp_desc[:10], kp_uv, kp_desc, radius=3.0, max_dist=10)
    assert pairs.tolist() == [[i, i] for i in range(10)]
    # too far: nothing within the radius
    assert len(match_by_projection(pred + 50.0, kp_desc[:10], kp_uv + 0.0, kp_desc, radius=3.0, max_dist=10)) <= 1
    # descriptor too different: rejected by the Hamming threshold
    assert len(match_by_projection(pred, 255 - kp_desc[:10], kp_uv, kp_desc, radius=3.0, max_dist=10)) == 0
    # two points claim keypoint 0: the closer descriptor keeps it
    d_far = kp_desc[0].copy()
    d_far[:2] ^= 0xFF  # 16 bits off
    pairs = match_by_projection(kp_uv[[0, 0]], np.stack([d_far, kp_desc[0]]), kp_uv, kp_desc, radius=2.0, max_dist=64)
    assert pairs.tolist() == [[1, 0]]


def test_binary_projection_matching_equals_the_generic_candidate_ranking():
    """The popcount / partition fast path for ORB descriptors returns exactly what ``best_pairs`` returns on the
    same candidates, ties included (few distinct descriptors make many equal distances)."""
    rng = np.random.default_rng(3)
    for trial in range(20):
        n, p = int(rng.integers(2, 400)), int(rng.integers(1, 400))
        kp_uv = rng.uniform(0, 100, (n, 2))
        palette = rng.integers(0, 256, (int(rng.integers(2, 12)), 32), dtype=np.uint8)
        kp_desc = palette[rng.integers(0, len(palette), n)]
        pt_desc = palette[rng.integers(0, len(palette), p)].copy()
        pt_desc[:, 0] ^= rng.integers(0, 4, p).astype(np.uint8)  # small perturbations: near-ties
        pred = rng.uniform(0, 100, (p, 2))
        radius = rng.uniform(3, 15, p) if trial % 2 else 8.0
        ratio = None if trial % 5 == 0 else 0.9
        got = match_by_projection(pred, pt_desc, kp_uv, kp_desc, radius, 64 if trial % 3 else 300, ratio)
        k = min(16, n)
        d, ki = cKDTree(kp_uv).query(pred, k=k, distance_upper_bound=float(np.max(radius)))
        d, ki = d.reshape(p, k), ki.reshape(p, k)
        valid = np.isfinite(d) & (d <= np.broadcast_to(radius, (p,))[:, None])
        qi, ti = np.nonzero(valid)[0], ki[valid].astype(np.int64)
        want = best_pairs(qi, ti, descriptor_rows(pt_desc[qi], kp_desc[ti]).astype(float), 64 if trial % 3 else 300, ratio)
        np.testing.assert_array_equal(got, want)


def test_bucketing_spreads_keypoints():
    # 1000 strong corners in one cell, 100 weak ones spread over the image
    rng = np.random.default_rng(2)
    dense = rng.uniform(0, 20, size=(1000, 2))
    spread = rng.uniform(0, 320, size=(100, 2))
    xy = np.vstack([dense, spread])
    resp = np.r_[np.full(1000, 10.0), np.full(100, 1.0)]
    keep = bucket(xy, resp, (240, 320), 200, 8, 6)
    assert len(keep) == 200
    assert np.sum(keep >= 1000) >= 90  # almost all spread keypoints survive


def _bucket_lexsort(xy, response, shape, n, cols, rows):
    """bucket written with two lexsorts: (cell, -response, index) ranks, then (rank, -response, index)."""
    if len(xy) <= n:
        return np.arange(len(xy))
    h, w = shape
    cx = np.clip((xy[:, 0] * cols / w).astype(np.int64), 0, cols - 1)
    cell = np.clip((xy[:, 1] * rows / h).astype(np.int64), 0, rows - 1) * cols + cx
    order = np.lexsort((np.arange(len(xy)), -response, cell))
    first = np.r_[0, np.flatnonzero(np.diff(cell[order])) + 1]
    rank = np.empty(len(xy), np.int64)
    rank[order] = np.arange(len(order)) - np.repeat(first, np.diff(np.r_[first, len(order)]))
    return np.sort(np.lexsort((np.arange(len(xy)), -response, rank))[:n])


def test_bucketing_equals_the_two_lexsort_ranking():
    """One argsort on (cell, strength rank) keys and a partition give the lexsort ranking's keypoints, equal
    responses included (ties by index)."""
    rng = np.random.default_rng(4)
    xy = rng.uniform([0, 0], [1241, 376], (4500, 2))
    for resp in (rng.gamma(2.0, 1e-3, 4500), rng.integers(0, 6, 4500).astype(float)):
        for n in (1, 150, 1500, 4499, 4500):
            np.testing.assert_array_equal(bucket(xy, resp, (376, 1241), n, 16, 12),
                                          _bucket_lexsort(xy, resp, (376, 1241), n, 16, 12))


def test_orb_extractor_on_synthetic_image():
    seq = SyntheticSequence(SyntheticConfig(n_frames=1, width=320, height=240, fx=262.5, fy=262.5, n_movers=0), sensor="rgbd")
    frame = next(iter(seq))
    assert "orb" in EXTRACTORS
    f = make_extractor(FeatureConfig(n_features=500)).detect(frame.image, seq.calibration.cam0)
    assert 300 < len(f) <= 500
    assert f.desc.shape == (len(f), 32) and f.uv.shape == f.raw.shape == (len(f), 2)
    np.testing.assert_allclose(f.uv, f.raw)  # the synthetic camera has no distortion
    # spread: every quadrant of the image holds keypoints
    q = (f.raw[:, 0] > 160).astype(int) + 2 * (f.raw[:, 1] > 120)
    assert np.bincount(q, minlength=4).min() > 30
    empty = make_extractor(FeatureConfig()).detect(np.zeros((240, 320), np.uint8), seq.calibration.cam0)
    assert len(empty) == 0


def test_orb_poor_light_second_pass_fills_a_dim_image_and_leaves_a_bright_one():
    seq = SyntheticSequence(SyntheticConfig(n_frames=1, width=320, height=240, fx=262.5, fy=262.5, n_movers=0), sensor="rgbd")
    img, cam = next(iter(seq)).image, seq.calibration.cam0
    dim = np.round(img.astype(np.float32) * 0.07).astype(np.uint8)  # 1/14 of the light, same scene
    on, off = make_extractor(FeatureConfig(n_features=500)), make_extractor(FeatureConfig(n_features=500, fast_threshold_min=12))
    bright_on, bright_off = on.detect(img, cam), off.detect(img, cam)
    np.testing.assert_array_equal(bright_on.raw, bright_off.raw)  # enough corners at the normal threshold: one pass
    np.testing.assert_array_equal(bright_on.desc, bright_off.desc)
    dim_on, dim_off = on.detect(dim, cam), off.detect(dim, cam)
    assert len(dim_off) < 0.5 * len(dim_on), (len(dim_off), len(dim_on))
    assert len(dim_on) > 250
    # most corners found at the normal threshold are still there (the lower one passes them too; a few lose the
    # non-maximum suppression to a new neighbour or their cell's bucket)
    d = np.linalg.norm(dim_off.raw[:, None] - dim_on.raw[None], axis=2).min(axis=1)
    assert np.mean(d < 0.5) > 0.75
    # a blurred image also has few corners, but at full contrast they are displaced ones: no second pass
    blur = cv2.GaussianBlur(img, (0, 0), 8.0)
    blur_on, blur_off = on.detect(blur, cam), off.detect(blur, cam)
    assert len(blur_off) < 250
    np.testing.assert_array_equal(blur_on.raw, blur_off.raw)


def _flip_bits(desc, n, rng):
    """Copy of (N,32) uint8 descriptors with n distinct bits flipped per row."""
    out = desc.copy()
    for row in out:
        for bit in rng.choice(256, n, replace=False):
            row[bit // 8] ^= np.uint8(1 << (bit % 8))
    return out


def test_epipolar_matching_finds_what_the_ratio_test_loses():
    """Two views of 300 points; every keypoint of view a has a twin in view b one bit further away than its
    true match (repetitive texture), which defeats a global ratio test; twins lie off the epipolar line.
    Points near the epipole (forward motion: no parallax) are skipped."""
    rng = np.random.default_rng(3)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    T_w_b = make_T(so3_exp(np.array([0.0, 0.03, 0.0])), np.array([0.3, 0.0, 0.5]))
    X = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(-2, 2, 300), rng.uniform(4, 10, 300)])
    Xb = X @ inv_T(T_w_b)[:3, :3].T + inv_T(T_w_b)[:3, 3]
    uv_a = X[:, :2] / X[:, 2:] * 500.0 + [320, 240]
    uv_true = Xb[:, :2] / Xb[:, 2:] * 500.0 + [320, 240] + rng.normal(0, 0.3, (300, 2))
    desc_a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    order = rng.permutation(600)  # b = true matches and twins, shuffled
    uv_b = np.vstack([uv_true, rng.uniform([0, 0], [640, 480], (300, 2))])[order]
    desc_b = np.vstack([_flip_bits(desc_a, 8, rng), _flip_bits(desc_a, 9, rng)])[order]
    truth = np.argsort(order)[:300]  # b index of a's true match
    assert len(match_mutual(desc_a, desc_b, ratio=0.75)) < 30  # the global ratio test keeps almost nothing
    T_b_a = inv_T(T_w_b)
    F = np.linalg.inv(K).T @ skew(T_b_a[:3, 3]) @ T_b_a[:3, :3] @ np.linalg.inv(K)
    epipole = (K @ T_b_a[:3, 3])[:2] / T_b_a[2, 3]
    m = match_epipolar(uv_a, desc_a, uv_b, desc_b, F, 2.0, epipole, 30.0, max_dist=50, ratio=0.7)
    correct = truth[m[:, 0]] == m[:, 1]
    near = np.linalg.norm(uv_true - epipole, axis=1) < 30.0
    assert correct.mean() > 0.97 and correct.sum() > 0.8 * (~near).sum()
    assert not near[m[:, 0]].any()
    assert len(np.unique(m[:, 1])) == len(m)


def _epipolar_reference(uv_a, desc_a, uv_b, desc_b, F, tol_b, epipole, min_px, max_dist, ratio):
    """match_epipolar written plainly: the whole (Na,Nb) band in float64, candidates through best_pairs."""
    lines = np.c_[uv_a, np.ones(len(uv_a))] @ F.T
    lines /= np.linalg.norm(lines[:, :2], axis=1)[:, None]
    ok = np.abs(lines[:, :2] @ uv_b.T + lines[:, 2:3]) <= np.broadcast_to(tol_b, (len(uv_b),))[None, :]
    ok &= (np.linalg.norm(uv_b - epipole, axis=1) >= min_px)[None, :]
    ia, jb = np.nonzero(ok)
    return best_pairs(ia, jb, hamming_rows(desc_a[ia], desc_b[jb]).astype(float), max_dist, ratio)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_epipolar_matching_equals_the_plain_band_search(seed):
    """The blocked float32 band test and the grouped best-pair search return what the plain float64 search
    does, pair for pair (random views, 1500 x 1400 keypoints, per-keypoint tolerances, repeated descriptors)."""
    rng = np.random.default_rng(seed)
    K = np.array([[700.0, 0, 600], [0, 700.0, 180], [0, 0, 1]])
    T_b_a = make_T(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.5, 3) + [0, 0, 1.0])
    F = np.linalg.inv(K).T @ skew(T_b_a[:3, 3]) @ T_b_a[:3, :3] @ np.linalg.inv(K)
    epipole = (K @ T_b_a[:3, 3])[:2] / T_b_a[2, 3]
    uv_a, uv_b = rng.uniform([0, 0], [1200, 370], (1500, 2)), rng.uniform([0, 0], [1200, 370], (1400, 2))
    lines = np.c_[uv_a[:700], np.ones(700)] @ F.T  # the first 700 of b on their twin's epipolar line, +-1 px
    x = rng.uniform(0, 1200, 700)
    uv_b[:700] = np.c_[x, -(lines[:, 0] * x + lines[:, 2]) / lines[:, 1] + rng.uniform(-1, 1, 700)]
    desc_a = rng.integers(0, 256, (1500, 32), dtype=np.uint8)
    desc_b = np.vstack([_flip_bits(desc_a[:700], 6, rng), rng.integers(0, 256, (700, 32), dtype=np.uint8)])
    tol = np.sqrt(3.84) * 1.2 ** rng.integers(0, 8, 1400)
    args = (uv_a, desc_a, uv_b, desc_b, F, tol, epipole, 10.0 * np.sqrt(1.2 ** rng.integers(0, 8, 1400)))
    want = _epipolar_reference(*args, max_dist=80, ratio=0.8)
    got = match_epipolar(*args, max_dist=80, ratio=0.8)
    assert len(want) > 20
    np.testing.assert_array_equal(got, want)
