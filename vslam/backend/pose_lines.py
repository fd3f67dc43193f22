"""Pose-only refinement with fixed points AND fixed Plücker lines (numpy), for tracking with lines.

Same scheme as ``pose_only.refine_pose`` (ORB-SLAM2 PoseOptimization: ``pose_rounds`` rounds of LM, chi2
classification of every observation after each, Huber in all rounds but the last) with line rows added:
each line observation contributes its two end-point distances (pixels, as ``line_factor.line_factor``),
Huber per observation (IRLS), chi2(2) test. The point rows reuse ``pose_only._linearize`` unchanged.

Parameterisation as in ``pose_only``: T_cam_world <- [Exp(w) | v] T_cam_world, so for a line
n_c <- n_c + w x n_c + v x d_c, i.e. dn_c/d(w, v) = [-[n_c]x, -[d_c]x].
"""

from __future__ import annotations

import numpy as np

from vslam.backend.line_factor import _skew_stack
from vslam.backend.pose_only import _MIN_OBS, _classify, _linearize, lm_pose
from vslam.backend.projection import chi2_thresholds, measurement_matrix
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import inv_T

_CHI2_LINE = 5.991  # 95 % of chi2(2)
_CHI2_BY_DOF = np.array([0.0, 3.841, 5.991, 7.815, 9.488])


def refine_pose_points_lines(
    T_world_cam: np.ndarray, pts_world: np.ndarray, uv: np.ndarray, ur: np.ndarray,
    lines_world: np.ndarray, segs: np.ndarray, K_L: np.ndarray, camera, cfg, line_sigma: float = 1.0,
    line_weight: float = 1.0, rho: np.ndarray | None = None, depth_weight: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (T_world_cam (4,4), point inliers (N,), line inliers (L,)).

    Points as in ``optimize_pose`` (world (N,3), uv (N,2), ur (N,) NaN = mono). lines_world: (L,6) Plücker;
    segs: (L,4) observed segments, ideal pixels; line_sigma px; line_weight scales the line rows' information.
    rho: (L,2) measured inverse depths of the end points (NaN: none) with whitening ``depth_weight`` (fx b /
    sigma, a virtual disparity); they add one row per end point and a chi2 degree of freedom each.
    With fewer than 3 points the line rows must carry the pose; with nothing usable the input comes back.
    """
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    pts = np.asarray(pts_world, dtype=np.float64).reshape(-1, 3)
    meas, stereo = measurement_matrix(uv, ur)
    if camera.baseline <= 0:
        stereo = np.zeros(len(pts), dtype=bool)
    vp = np.isfinite(pts).all(axis=1) & np.isfinite(meas[:, :2]).all(axis=1)
    Lw = np.asarray(lines_world, dtype=np.float64).reshape(-1, 6)
    sg = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    vl = np.isfinite(Lw).all(axis=1) & np.isfinite(sg).all(axis=1)
    P, Z, S = pts[vp], meas[vp], stereo[vp]
    w = np.full(len(P), 1.0 / cfg.pixel_sigma)
    thr = chi2_thresholds(S, cfg.chi2_mono, cfg.chi2_stereo)
    L, G = Lw[vl], sg[vl]
    lw = np.sqrt(line_weight) / line_sigma
    D = None
    if rho is not None and depth_weight > 0:
        D = (np.asarray(rho, dtype=np.float64).reshape(-1, 2)[vl], pl.end_rays(G, K_L), np.sqrt(line_weight) * depth_weight)
    pin, lin = np.zeros(len(pts), bool), np.zeros(len(Lw), bool)
    T_cw = inv_T(T_world_cam)
    if len(P) + len(L) < _MIN_OBS:
        return T_world_cam.copy(), pin, lin
    ap, al = np.ones(len(P), bool), np.ones(len(L), bool)
    for rnd in range(cfg.pose_rounds):
        if ap.sum() + al.sum() < _MIN_OBS:
            break
        k = cfg.huber_k if rnd < cfg.pose_rounds - 1 else None
        T_cw = _lm(T_cw, P[ap], Z[ap], S[ap], w[ap], L[al], G[al], _sub(D, al), K_L, lw, camera, k, cfg.pose_iterations)
        ap = _classify(T_cw, P, Z, S, 1.0 / w, thr, camera) if len(P) else ap
        al = _line_chi2(T_cw, L, G, D, K_L, lw) <= _line_thresholds(D, len(L))
    pin[vp], lin[vl] = ap, al
    return inv_T(T_cw), pin, lin


def _sub(D, idx):
    return None if D is None else (D[0][idx], D[1][idx], D[2])


def _line_thresholds(D, n: int) -> np.ndarray:
    """95 % of chi2(2 + end points with a depth)."""
    if D is None:
        return np.full(n, _CHI2_LINE)
    return _CHI2_BY_DOF[2 + np.isfinite(D[0]).sum(axis=1)]


def _line_chi2(T_cw, L, G, D, K_L, lw) -> np.ndarray:
    if len(L) == 0:
        return np.zeros(0)
    e, _, _ = _line_block(T_cw, L, G, D, K_L, lw, False)
    chi2 = np.sum(e * e, axis=1)
    return np.where(np.isfinite(chi2), chi2, np.inf)


def _line_block(T_cw, L, G, D, K_L, lw, jac: bool):
    """Whitened residuals (L,2), or (L,4) with end-point depths D = (rho (L,2), rays (L,2,3), weight), and
    with jac d e / d(w, v) (L,2|4,6) of the left update. An end point without a depth gets zero rows."""
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    nc = L[:, :3] @ R.T + np.cross(t, L[:, 3:] @ R.T)
    dc = L[:, 3:] @ R.T
    l = nc @ K_L.T
    rho2 = l[:, 0] ** 2 + l[:, 1] ** 2
    rho = np.sqrt(rho2)
    x = np.ones((len(L), 2, 3))
    x[:, 0, :2], x[:, 1, :2] = G[:, :2], G[:, 2:]
    xl = (x @ l[:, :, None])[:, :, 0]
    e = xl * (lw / rho)[:, None]
    if D is not None:
        r_obs, rays, dw = D
        r_pred, dn, dd = pl.inverse_depth(nc, dc, rays, jac)
        ed = dw * (r_obs - r_pred)
        has = np.isfinite(ed)
        e = np.concatenate([e, np.where(has, ed, 0.0)], axis=1)
    if not jac:
        return e, None, None
    l01 = l.copy()
    l01[:, 2] = 0.0
    Gd = (x / rho[:, None, None] - (xl / (rho2 * rho)[:, None])[:, :, None] * l01[:, None, :]) @ (K_L * lw)
    if D is not None:  # e_d = -dw rho(n_c, d_c): d e_d / d n_c here, d e_d / d d_c below
        Gd = np.concatenate([Gd, np.where(has[:, :, None], -dw * dn, 0.0)], axis=1)
    # n_c <- n_c - [n_c]x w - [d_c]x v, d_c <- d_c - [d_c]x w
    J = -(Gd @ np.concatenate([_skew_stack(nc), _skew_stack(dc)], axis=2))
    if D is not None:
        J[:, 2:, :3] -= np.where(has[:, :, None], -dw * dd, 0.0) @ _skew_stack(dc)
    return e, J, None


def _cost_H_g(R, t, P, Z, S, w, L, G, D, K_L, lw, camera, huber_k):
    cost, H, g = 0.0, np.zeros((6, 6)), np.zeros(6)
    if len(P):
        cost, H, g = _linearize(R, t, np.ascontiguousarray(P.T), np.ascontiguousarray(Z.T), S.astype(np.float64), w,
                                camera, huber_k)
    if len(L):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        e, J, _ = _line_block(T, L, G, D, K_L, lw, True)
        a = np.linalg.norm(e, axis=1)
        a = np.where(np.isfinite(a), a, 0.0)
        e, J = np.nan_to_num(e), np.nan_to_num(J)
        if huber_k is None:
            sw, rho = np.ones(len(L)), 0.5 * a * a
        else:
            big = a > huber_k
            sw = np.where(big, np.sqrt(huber_k / np.where(big, a, 1.0)), 1.0)
            rho = np.where(big, huber_k * (a - 0.5 * huber_k), 0.5 * a * a)
        Jw = (J * sw[:, None, None]).reshape(-1, 6)
        ew = (e * sw[:, None]).reshape(-1)
        cost += float(rho.sum())
        H = H + Jw.T @ Jw
        g = g + Jw.T @ ew
    return cost, H, g


def _lm(T_cw, P, Z, S, w, L, G, D, K_L, lw, camera, huber_k, iterations) -> np.ndarray:
    """LM on points + lines (``pose_only.lm_pose`` with this cost)."""
    return lm_pose(T_cw, lambda R, t: _cost_H_g(R, t, P, Z, S, w, L, G, D, K_L, lw, camera, huber_k), iterations)
