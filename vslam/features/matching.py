"""Descriptor matching: mutual nearest neighbours with a ratio test, and
projection-guided matching of map points into a frame.

Binary descriptors use Hamming distance (bits), float descriptors L2. Every threshold in the configs is in
bits of a 256-bit ORB descriptor; a float (unit-length) descriptor's L2 distance is reported in the same
unit, scaled by ``BITS_PER_L2`` so that unrelated descriptors sit where unrelated ORB descriptors do (128
bits apart; orthogonal unit vectors are sqrt(2) apart). ORB's 64-bit match limit is then an L2 of 0.71,
the usual SuperPoint matching threshold (0.7). Everything is vectorised; ties are broken by index so
results are deterministic.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.int32)
BITS_PER_L2 = 128.0 / np.sqrt(2.0)


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of (M,D) uint8 descriptor pairs -> (M,) int bits."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1)


def descriptor_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance of paired descriptors in bits: Hamming for uint8, ``BITS_PER_L2`` x L2 for float."""
    if a.dtype == np.uint8:
        return hamming_rows(a, b)
    return BITS_PER_L2 * np.linalg.norm(a.astype(np.float32) - b.astype(np.float32), axis=1)


def match_mutual(d1: np.ndarray, d2: np.ndarray, ratio: float | None = 0.8, max_dist: float = np.inf) -> np.ndarray:
    """(M,2) index pairs (i in d1, j in d2): mutual nearest neighbours passing Lowe's ratio test (none when
    ``ratio`` is None: the feature benchmark scores the descriptor alone). ``max_dist`` in bits (module docstring)."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros((0, 2), np.int64)
    if d1.dtype != np.uint8:
        return _mutual_float(d1, d2, ratio, max_dist / BITS_PER_L2)
    if hasattr(np, "bitwise_count") and d1.shape[1] % 8 == 0:
        return _mutual_binary(d1, d2, ratio, max_dist)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(d1, d2, k=2)
    bwd = np.full(len(d2), -1, np.int64)
    for m in bf.knnMatch(d2, d1, k=1):
        if m:
            bwd[m[0].queryIdx] = m[0].trainIdx
    pairs = [
        (m[0].queryIdx, m[0].trainIdx) for m in fwd
        if len(m) == 2 and (ratio is None or m[0].distance < ratio * m[1].distance) and m[0].distance <= max_dist
        and bwd[m[0].trainIdx] == m[0].queryIdx
    ]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


_MUTUAL_BLOCK = 128  # rows of the (N1,N2) Hamming matrix at a time (a block of ~1500 columns stays in cache)


def _mutual_binary(d1: np.ndarray, d2: np.ndarray, ratio: float | None, max_dist: float) -> np.ndarray:
    """``match_mutual`` for binary descriptors: the pairs of OpenCV's two brute-force k-NN passes (best and second
    best per row, best per column; ties to the lower index) from one Hamming matrix, built a block of rows at a
    time by 64-bit popcount: OpenCV computes every distance once per direction (docs/speed.md;
    tests/features/test_matching.py checks the pairs against OpenCV's)."""
    n1, n2 = len(d1), len(d2)
    a = np.ascontiguousarray(d1).view(np.uint64)  # (N1,W)
    bt = np.ascontiguousarray(np.ascontiguousarray(d2).view(np.uint64).T)  # (W,N2): one row per word
    big = np.iinfo(np.int32).max
    best_j = np.empty(n1, np.int64)
    best_d = np.empty(n1, np.int64)
    second_d = np.empty(n1, np.int64)
    col_key = np.full(n2, big, np.int32)  # per column min of distance * N1 + row: its nearest row, lowest on ties
    words = np.empty((_MUTUAL_BLOCK, n2), np.uint64)
    bits = np.empty((_MUTUAL_BLOCK, n2), np.uint8)
    for s in range(0, n1, _MUTUAL_BLOCK):
        blk = a[s:s + _MUTUAL_BLOCK]
        m = len(blk)
        w, c = words[:m], bits[:m]
        D = np.zeros((m, n2), np.uint16)
        for k in range(bt.shape[0]):
            np.bitwise_xor(blk[:, k, None], bt[k], out=w)
            np.bitwise_count(w, out=c)
            D += c
        r = np.arange(m)
        j = D.argmin(axis=1)  # the first minimum: the lowest column on ties
        d = D[r, j]
        D[r, j] = np.iinfo(np.uint16).max
        second_d[s:s + m] = D.min(axis=1)
        D[r, j] = d
        best_j[s:s + m], best_d[s:s + m] = j, d
        key = D.astype(np.int32)
        key *= n1
        key += (s + r)[:, None]
        np.minimum(col_key, key.min(axis=0), out=col_key)
    rows = np.arange(n1)
    ok = (col_key[best_j] % n1 == rows) & (best_d <= max_dist)
    if ratio is not None:
        ok &= best_d < ratio * second_d
    return np.stack([rows[ok], best_j[ok]], axis=1).reshape(-1, 2)


def _mutual_float(d1: np.ndarray, d2: np.ndarray, ratio: float | None, max_l2: float) -> np.ndarray:
    """``match_mutual`` for float descriptors from one (N1,N2) matrix product, squared L2 = |a|^2 + |b|^2 - 2 a.b:
    both directions read the same matrix (OpenCV's brute force matcher computes every distance once per direction,
    several times slower; docs/speed.md, 'Small exact speed-ups quoted in code comments'). Ties go to the lower
    index."""
    a = np.ascontiguousarray(d1, dtype=np.float32)
    b = np.ascontiguousarray(d2, dtype=np.float32)
    D = a @ b.T
    D *= -2.0
    D += np.einsum("ij,ij->i", a, a)[:, None]
    D += np.einsum("ij,ij->i", b, b)[None, :]
    r = np.arange(len(a))
    j1 = D.argmin(axis=1)
    d1st = D[r, j1].copy()
    D[r, j1] = np.inf
    d2nd = D[r, D.argmin(axis=1)]
    D[r, j1] = d1st
    # each column's nearest row, the lowest on ties (argmin down the columns is much slower: strided)
    rows, cols = np.nonzero(D == D.min(axis=0))
    _, first = np.unique(cols, return_index=True)
    bwd = np.full(len(b), -1, np.int64)
    bwd[cols[first]] = rows[first]
    best, second = np.sqrt(np.maximum(d1st, 0.0)), np.sqrt(np.maximum(d2nd, 0.0))
    ok = (bwd[j1] == r) & (best <= max_l2)
    if ratio is not None:
        ok &= best < ratio * second
    return np.stack([r[ok], j1[ok]], axis=1).astype(np.int64).reshape(-1, 2)


def match_by_projection(
    pred_uv: np.ndarray,
    pt_desc: np.ndarray,
    kp_uv: np.ndarray,
    kp_desc: np.ndarray,
    radius: float | np.ndarray,
    max_dist: float = 64,
    ratio: float = 0.9,
    kp_tree: cKDTree | None = None,
    max_candidates: int = 16,
) -> np.ndarray:
    """Guided matching: for each predicted map-point pixel the best keypoint within ``radius``.

    pred_uv: (P,2) predicted ideal pixels of map points; pt_desc: (P,D) their descriptors.
    kp_uv: (N,2) ideal pixels of the frame's keypoints; kp_desc: (N,D).
    radius: pixels, scalar or (P,) (wider for coarse octaves / uncertain predictions).
    Returns (M,2) pairs (point index, keypoint index); each keypoint used at most once
    (the closest descriptor wins), best distance <= max_dist and < ratio x second best.
    Only the ``max_candidates`` keypoints nearest to the prediction are compared (a fixed-size,
    fully vectorised k-d tree query).
    """
    empty = np.zeros((0, 2), np.int64)
    if len(pred_uv) == 0 or len(kp_uv) == 0:
        return empty
    tree = kp_tree if kp_tree is not None else cKDTree(kp_uv)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(pred_uv),))
    k = min(max_candidates, len(kp_uv))
    d, ki = tree.query(pred_uv, k=k, distance_upper_bound=float(r.max()))
    d, ki = d.reshape(len(pred_uv), k), ki.reshape(len(pred_uv), k)
    valid = np.isfinite(d) & (d <= r[:, None])
    if not valid.any():
        return empty
    if pt_desc.dtype == np.uint8 and kp_desc.dtype == np.uint8 and pt_desc.shape[1] % 8 == 0:
        return _best_pairs_binary(valid, ki, pt_desc, kp_desc, max_dist, ratio)
    if pt_desc.dtype == np.float32 and kp_desc.dtype == np.float32:
        return _best_pairs_float(valid, ki, pt_desc, kp_desc, max_dist, ratio)
    pi = np.nonzero(valid)[0]
    ki = ki[valid].astype(np.int64)
    return best_pairs(pi, ki, descriptor_rows(pt_desc[pi], kp_desc[ki]).astype(np.float64), max_dist, ratio)


def _best_pairs_binary(valid: np.ndarray, ki: np.ndarray, pt_desc: np.ndarray, kp_desc: np.ndarray, max_dist: float,
                       ratio: float | None) -> np.ndarray:
    """``best_pairs`` on the (P,k) candidate grid of binary descriptors, same result, faster: Hamming
    distances by 64-bit popcount, and each row's best / second best from one partition of the key
    distance * (N+1) + target (integer distances, so ties still break by target index)."""
    n = len(kp_desc)
    big = np.iinfo(np.int64).max
    # distances of the candidates within the radius only (~20 % at 4 px); flat indices: 1-D nonzero and
    # gathers are several times faster than their 2-D forms
    flat = np.flatnonzero(valid)
    pi = flat // valid.shape[1]
    kv = ki.ravel()[flat].astype(np.int64)
    dist = hamming_pairs(pt_desc, kp_desc, pi, kv)
    key = np.full(valid.size, big, np.int64)
    key[flat] = dist * (n + 1) + kv
    key = key.reshape(valid.shape)
    two = np.partition(key, 1, axis=1)[:, :2] if key.shape[1] > 1 else np.concatenate([key, np.full_like(key, big)], axis=1)
    has = two[:, 0] != big
    best_q = np.flatnonzero(has)
    best_d, best_t = np.divmod(two[has, 0], n + 1)
    ok = best_d <= max_dist
    if ratio is not None:
        sec = np.where(two[has, 1] != big, two[has, 1] // (n + 1), np.inf)
        ok &= best_d < ratio * sec
    return _one_per_target(best_q[ok], best_t[ok], best_d[ok])


def _best_pairs_float(valid: np.ndarray, ki: np.ndarray, pt_desc: np.ndarray, kp_desc: np.ndarray, max_dist: float,
                      ratio: float | None) -> np.ndarray:
    """``best_pairs`` on the (P,k) candidate grid of float32 descriptors, same result (the same float32 L2 per
    pair), without its sort: each row's best is the smallest distance, the lowest target among equal ones; its
    second best the smallest of the rest (equal to the best on a tie, as in the sorted order)."""
    big = np.iinfo(np.int64).max
    flat = np.flatnonzero(valid)
    pi = flat // valid.shape[1]
    kv = ki.ravel()[flat].astype(np.int64)
    # np.linalg.norm's own arithmetic (x * x, add.reduce over the row, sqrt), in place: the same float32 distances
    diff = np.take(pt_desc, pi, axis=0)
    diff -= np.take(kp_desc, kv, axis=0)
    diff *= diff
    d = BITS_PER_L2 * np.sqrt(np.add.reduce(diff, axis=1))
    D = np.full(valid.shape, np.inf)
    D.ravel()[flat] = d.astype(np.float64)
    T = np.full(valid.shape, big, np.int64)
    T.ravel()[flat] = kv
    has = valid.any(axis=1)
    best_d = D.min(axis=1)
    col = np.where(D == best_d[:, None], T, big).argmin(axis=1)  # the lowest target among the row's best
    rows = np.arange(len(D))
    best_t = T[rows, col]
    D[rows, col] = np.inf
    sec = D.min(axis=1)
    ok = has & (best_d <= max_dist)
    if ratio is not None:
        ok &= best_d < ratio * sec
    return _one_per_target(rows[ok], best_t[ok], best_d[ok])


def best_pairs(qi: np.ndarray, ti: np.ndarray, dist: np.ndarray, max_dist: float, ratio: float | None) -> np.ndarray:
    """From candidate pairs (query qi, target ti, descriptor distance dist), each (M,): per query its closest
    target, kept when <= max_dist and (ratio not None) < ratio x the query's second-best distance; then one
    query per target, the smallest distance winning. Ties break by index, so the result is deterministic.
    -> (K,2) (query, target) sorted by query."""
    order = np.lexsort((ti, dist, qi))
    qi, ti, dist = qi[order], ti[order], dist[order]
    first = np.r_[True, qi[1:] != qi[:-1]] if len(qi) else np.zeros(0, bool)
    best_q, best_t, best_d = qi[first], ti[first], dist[first]
    ok = best_d <= max_dist
    if ratio is not None:
        second = np.r_[False, first[:-1]] & ~first
        sec = np.full(int(qi.max()) + 1 if len(qi) else 0, np.inf)
        sec[qi[second]] = dist[second]
        ok &= best_d < ratio * sec[best_q]
    return _one_per_target(best_q[ok], best_t[ok], best_d[ok])


def _one_per_target(best_q: np.ndarray, best_t: np.ndarray, best_d: np.ndarray) -> np.ndarray:
    """Each query's best target -> one query per target (smallest distance, then lowest query index) as
    (K,2) (query, target) pairs sorted by query."""
    order = np.lexsort((best_q, best_d, best_t))
    best_q, best_t = best_q[order], best_t[order]
    keep = np.r_[True, best_t[1:] != best_t[:-1]] if len(best_t) else np.zeros(0, bool)
    out = np.stack([best_q[keep], best_t[keep]], axis=1).astype(np.int64).reshape(-1, 2)
    return out[np.argsort(out[:, 0], kind="stable")]


_EPI_BLOCK = 128  # rows of match_epipolar's band test at a time: (128, ~2000) float32 stays in cache


def match_epipolar(
    uv_a: np.ndarray,
    desc_a: np.ndarray,
    uv_b: np.ndarray,
    desc_b: np.ndarray,
    F_ba: np.ndarray,
    tol_b: np.ndarray | float,
    epipole_b: np.ndarray | None = None,
    min_epipole_px: np.ndarray | float = 0.0,
    max_dist: float = 50,
    ratio: float = 0.6,
) -> np.ndarray:
    """Matches for triangulation, searched along epipolar lines (ORB-SLAM's ``SearchForTriangulation``).

    uv_a (Na,2), uv_b (Nb,2): ideal pixels of two keyframes' unmatched keypoints; desc_a, desc_b their
    descriptors; F_ba (3,3): fundamental matrix with x_b^T F_ba x_a = 0; tol_b: pixels, scalar or (Nb,)
    (the keypoint's octave scale times a chi2(1) bound); epipole_b (2,): camera a's centre in image b,
    keypoints closer than min_epipole_px (scalar or (Nb,)) to it are skipped (no depth can be triangulated
    along the baseline -- forward motion). Returns (M,2) pairs (i in a, j in b): the best candidate within
    tol_b of a's epipolar line, <= max_dist and < ratio x the second best; each j used once (smallest
    distance wins). Compared with a global mutual-NN + ratio test, the epipolar band removes almost every
    distractor, so far more true matches survive the ratio test (repetitive street texture).
    """
    empty = np.zeros((0, 2), np.int64)
    if len(uv_a) == 0 or len(uv_b) == 0:
        return empty
    tol = np.broadcast_to(np.asarray(tol_b, dtype=np.float64), (len(uv_b),))
    cols = np.arange(len(uv_b))
    if epipole_b is not None:  # keypoints near the epipole leave the search before the (Na,Nb) band test
        far = np.linalg.norm(uv_b - epipole_b, axis=1) >= np.broadcast_to(np.asarray(min_epipole_px, np.float64), (len(uv_b),))
        cols = cols[far]
    if len(cols) == 0:
        return empty
    lines = np.c_[uv_a, np.ones(len(uv_a))] @ F_ba.T  # (Na,3) epipolar line in b of each a
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-12)[:, None]
    # The band test is the bulk of the work (Na x Nb in the millions on KITTI keyframes): in float32 and in blocks
    # of rows that stay in cache, faster than one float64 (Na,Nb) matrix. A pair within ~1e-4 px of the band's edge may
    # fall the other way than in float64 (the same input still gives the same pairs).
    n_rows, la, lc = _EPI_BLOCK, lines[:, :2].astype(np.float32), lines[:, 2:3].astype(np.float32)
    ub, tb = np.ascontiguousarray(uv_b[cols].T, dtype=np.float32), tol[cols].astype(np.float32)[None, :]
    n_c = len(cols)
    flat = []
    for s in range(0, len(la), n_rows):
        dist = la[s:s + n_rows] @ ub  # (rows,Nc) pixels from each line
        dist += lc[s:s + n_rows]
        np.abs(dist, out=dist)
        # flat indices: a 1-D nonzero is several times faster than the 2-D one (two index arrays)
        flat.append(np.flatnonzero(dist <= tb) + s * n_c)  # sorted by row, then column
    ia, jc = np.divmod(np.concatenate(flat), n_c)
    jb = cols[jc]
    if len(ia) == 0:
        return empty
    if desc_a.dtype == np.uint8:
        return best_sorted(ia, jb, hamming_pairs(desc_a, desc_b, ia, jb), len(uv_b), max_dist, ratio)
    return best_pairs(ia, jb, descriptor_rows(desc_a[ia], desc_b[jb]).astype(np.float64), max_dist, ratio)


def hamming_pairs(desc_a: np.ndarray, desc_b: np.ndarray, ia: np.ndarray, jb: np.ndarray) -> np.ndarray:
    """Hamming distances (M,) int64 of desc_a[ia] and desc_b[jb]: 64-bit words and a hardware popcount where the
    descriptors allow it (numpy >= 2.0, width a multiple of 8 bytes), else the byte table. Rows are gathered with
    ``np.take`` (a 2-D fancy index copies row by row, several times slower) and the per-word popcounts (uint8,
    each <= 64) summed column by column."""
    if hasattr(np, "bitwise_count") and desc_a.shape[1] % 8 == 0:
        x = np.take(np.ascontiguousarray(desc_a).view(np.uint64), ia, axis=0)
        x ^= np.take(np.ascontiguousarray(desc_b).view(np.uint64), jb, axis=0)
        cnt = np.bitwise_count(x)
        dist = cnt[:, 0].astype(np.int64)
        for col in range(1, cnt.shape[1]):  # a few columns: faster than a reduction over a short axis
            dist += cnt[:, col]
        return dist
    return hamming_rows(desc_a[ia], desc_b[jb]).astype(np.int64)


def best_sorted(qi: np.ndarray, ti: np.ndarray, dist: np.ndarray, n_targets: int, max_dist: float,
                ratio: float | None) -> np.ndarray:
    """``best_pairs`` for integer distances and candidates grouped by query (qi ascending): the best and second
    best per query by a minimum over each group (no sort), same pairs as ``best_pairs``."""
    key = dist * n_targets + ti  # unique within a query: (distance, target) order as best_pairs' lexsort
    starts = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
    best = np.minimum.reduceat(key, starts)
    best_d, best_t = np.divmod(best, n_targets)
    ok = best_d <= max_dist
    if ratio is not None:
        big = np.iinfo(np.int64).max
        rest = np.where(key == np.repeat(best, np.diff(np.r_[starts, len(key)])), big, key)
        second = np.minimum.reduceat(rest, starts)
        sec_d = np.where(second != big, second // n_targets, np.inf)
        ok &= best_d < ratio * sec_d
    return _one_per_target(qi[starts][ok], best_t[ok], best_d[ok].astype(np.float64))
