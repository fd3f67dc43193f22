"""Stereo depth on a rectified rig (KITTI, the synthetic rig): row-guided descriptor matching, then
ORB-SLAM2's sub-pixel refinement (``Frame::ComputeStereoMatches``, Mur-Artal & Tardós 2017).

Why not the generic path of ``depth.depth_stereo``: its global mutual-NN match has no row constraint, and
the disparity of two ORB keypoints is quantised to their pyramid level (1.2^l px): at 2-4 m and a 10 cm
baseline that is a depth error of several per cent, which local BA cannot average away. Here:

1. Candidates: right keypoints on the left keypoint's row (|v_l - v_r| <= 2 x 1.2^octave), within the
   disparity range of [min_depth, max_depth], octave within one level; the best descriptor distance (bits, ``matching``) <=
   ``max_hamming`` wins, one left keypoint per right keypoint.
2. Refinement on the left keypoint's pyramid level: sum of absolute differences of an 11x11 patch along the
   row, offsets -5..5 around the matched right x, parabola through the minimum and its neighbours;
   rejected when the minimum sits at the search edge or the parabola moves it by more than a pixel.
3. Matches whose SAD exceeds 2.1 x the median are dropped (ORB-SLAM2's 1.5 x 1.4 x median).

The disparity is then measured to a fraction of a pixel *relative to the left keypoint*, which is what
``StereoCamera.disparity_sigma`` models.
"""

from __future__ import annotations

import cv2
import numpy as np

from vslam.data.types import Calibration
from vslam.features.base import Features
from vslam.features.matching import best_pairs, best_sorted, descriptor_rows, hamming_pairs

_W = 5  # half patch
_L = 5  # half search range (pixels of the keypoint's level)


def is_rectified(calib: Calibration, tol: float = 1e-6) -> bool:
    """cam1 = cam0 shifted along +x, same pinhole, no distortion: rows are epipolar lines."""
    c0, c1, T = calib.cam0, calib.cam1, calib.T_cam0_cam1
    if c1 is None or T is None or c0.is_distorted or c1.is_distorted:
        return False
    same_k = np.allclose([c0.fx, c0.fy, c0.cx, c0.cy], [c1.fx, c1.fy, c1.cx, c1.cy], atol=tol)
    return bool(same_k and np.allclose(T[:3, :3], np.eye(3), atol=tol) and abs(T[1, 3]) < tol
                and abs(T[2, 3]) < tol and T[0, 3] > 0)


def pyramid(gray: np.ndarray, scale_factor: float, n_levels: int) -> list[np.ndarray]:
    """Levels resized like OpenCV's ORB (level l: size / scale_factor^l, bilinear), uint8 like ``gray``."""
    h, w = gray.shape[:2]
    out = [gray]
    for lvl in range(1, n_levels):
        s = scale_factor**lvl
        out.append(cv2.resize(gray, (int(round(w / s)), int(round(h / s))), interpolation=cv2.INTER_LINEAR))
    return out


def _row_matches(left: Features, right: Features, fx_b: float, min_depth: float, max_depth: float,
                 max_hamming: int) -> tuple[np.ndarray, np.ndarray]:
    """(left idx, right idx) of the best row-band candidate per left keypoint (step 1).

    Candidates come from the right keypoints sorted by row (ORB-SLAM2's row index): each left keypoint reads
    the run of right keypoints within its band, so the work grows with the pairs in the bands, not with
    N_left x N_right (docs/speed.md; tests/features/test_stereo.py checks it against the full pair matrix)."""
    dl, dr = left.uv, right.uv
    band = 2.0 * left.level_scale()
    order = np.argsort(dr[:, 1], kind="stable")
    vr = dr[order, 1]
    # the band's rows, widened by a hair: rounding of v -/+ band cannot drop a pair the exact test below keeps
    lo = np.searchsorted(vr, dl[:, 1] - band - 1e-6, side="left")
    n = np.maximum(np.searchsorted(vr, dl[:, 1] + band + 1e-6, side="right") - lo, 0)
    il = np.repeat(np.arange(len(dl)), n)  # ascending: candidates grouped by left keypoint
    ir = order[np.arange(len(il)) - np.repeat(np.cumsum(n) - n - lo, n)]
    disp = dl[il, 0] - dr[ir, 0]
    ok = (np.abs(dl[il, 1] - dr[ir, 1]) <= band[il]) & (disp >= fx_b / max_depth) & (disp <= fx_b / min_depth)
    ok &= np.abs(left.octave[il] - right.octave[ir]) <= 1
    il, ir = il[ok], ir[ok]
    if len(il) == 0:
        return il, ir
    if left.desc.dtype == np.uint8:
        pairs = best_sorted(il, ir, hamming_pairs(left.desc, right.desc, il, ir), len(right), max_hamming, None)
    else:
        pairs = best_pairs(il, ir, descriptor_rows(left.desc[il], right.desc[ir]).astype(np.float64), max_hamming, None)
    return pairs[:, 0], pairs[:, 1]


def _refine(img_l: np.ndarray, img_r: np.ndarray, xl: np.ndarray, y: np.ndarray, xr: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """One pyramid level (grey images): integer left (xl, y), right guess xr (K,) level pixels ->
    (sub-pixel right x (K,), SAD (K,)); NaN where the patch leaves the image or the minimum is not interior."""
    h, w = img_l.shape
    k = len(xl)
    out, sad = np.full(k, np.nan), np.full(k, np.inf)
    ok = (y - _W >= 0) & (y + _W < h) & (xl - _W >= 0) & (xl + _W < w) & (xr - _W - _L - 1 >= 0) & (xr + _W + _L + 1 < w)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return out, sad
    offs = np.arange(-_L - 1, _L + 2)  # one extra on each side for the parabola at the edges
    # patches copied as windows of the images, one block per keypoint: (K,11,11) left, and one (K,11,23) strip
    # right whose 13 windows are the right patches at the offsets
    win_l = np.lib.stride_tricks.sliding_window_view(img_l, (2 * _W + 1, 2 * _W + 1))
    win_r = np.lib.stride_tricks.sliding_window_view(img_r, (2 * _W + 1, 2 * (_W + _L + 1) + 1))
    pl = win_l[y[idx] - _W, xl[idx] - _W].astype(np.int16)
    pl = pl - pl[:, _W:_W + 1, _W:_W + 1]  # ORB-SLAM2 subtracts the centre pixel (brightness offset)
    strip = win_r[y[idx] - _W, xr[idx] - _W - _L - 1].astype(np.int16)
    win = np.lib.stride_tricks.sliding_window_view(strip, 2 * _W + 1, axis=2).transpose(0, 2, 1, 3)  # offset, row, col
    pr = np.empty((len(idx), len(offs), 2 * _W + 1, 2 * _W + 1), np.int16)  # C order: each patch's SAD sums in place
    np.subtract(win, strip[:, _W, _W:_W + len(offs), None, None], out=pr)  # minus each window's centre pixel
    np.subtract(pl[:, None], pr, out=pr)  # within +-510: int16 holds it
    np.abs(pr, out=pr)
    d = pr.reshape(len(idx), len(offs), -1).sum(axis=2, dtype=np.int32).astype(np.float64)  # (K,13)
    best = np.argmin(d[:, 1:-1], axis=1) + 1
    interior = (best > 1) & (best < len(offs) - 2)
    r = np.arange(len(idx))
    d0, dm, dp = d[r, best], d[r, best - 1], d[r, best + 1]
    # ORB-SLAM2's parabola. Its vertex is pulled towards the integer offset (tests/features/test_stereo.py);
    # the equiangular (V) fit SAD suggests gave worse depths on the synthetic rig, so the parabola stays
    # (docs/features.md, 'Measurements behind settings in the code').
    den = 2.0 * (dm + dp - 2.0 * d0)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den > 0, (dm - dp) / den, np.nan)
    good = interior & (np.abs(delta) < 1.0)
    out[idx[good]] = xr[idx[good]] + offs[best[good]] + delta[good]
    sad[idx[good]] = d0[good]
    return out, sad


def depth_stereo_rectified(left_img: np.ndarray, right_img: np.ndarray, left: Features, right: Features,
                           calib: Calibration, min_depth: float, max_depth: float, max_hamming: int = 75,
                           n_levels: int = 8) -> np.ndarray:
    """(N,) depth (metres, cam0 z) of each left keypoint, NaN where unmatched; the steps are in the module doc.
    left_img / right_img: BGR or grey images of the rectified pair; left/right: their ORB features."""
    z = np.full(len(left), np.nan)
    if len(left) == 0 or len(right) == 0:
        return z
    fx_b = calib.cam0.fx * float(calib.T_cam0_cam1[0, 3])
    il, ir = _row_matches(left, right, fx_b, min_depth, max_depth, max_hamming)
    if len(il) == 0:
        return z
    gl = left_img if left_img.ndim == 2 else cv2.cvtColor(left_img, cv2.COLOR_BGR2GRAY)
    gr = right_img if right_img.ndim == 2 else cv2.cvtColor(right_img, cv2.COLOR_BGR2GRAY)
    n_levels = max(n_levels, int(left.octave.max()) + 1)
    pyr_l, pyr_r = pyramid(gl, left.scale_factor, n_levels), pyramid(gr, left.scale_factor, n_levels)
    disp, sad = np.full(len(il), np.nan), np.full(len(il), np.inf)
    for lvl in np.unique(left.octave[il]).tolist():
        sel = np.flatnonzero(left.octave[il] == lvl)
        s = left.scale_factor**lvl
        xl = np.round(left.raw[il[sel], 0] / s).astype(np.int64)
        y = np.round(left.raw[il[sel], 1] / s).astype(np.int64)
        xr = np.round(right.raw[ir[sel], 0] / s).astype(np.int64)
        x_sub, sad[sel] = _refine(pyr_l[lvl], pyr_r[lvl], xl, y, xr)
        disp[sel] = (xl - x_sub) * s  # full-resolution disparity, relative to the left keypoint
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = fx_b / disp
    ok = np.isfinite(depth) & (depth >= min_depth) & (depth <= max_depth)
    if ok.any():
        ok &= sad <= 2.1 * np.median(sad[ok])
    z[il[ok]] = depth[ok]
    return z
