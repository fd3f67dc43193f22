"""Pose-only refinement with fixed 3-D points: vectorised numpy Levenberg-Marquardt / IRLS on SE(3).

Scheme of ORB-SLAM2 ``Optimizer::PoseOptimization`` (Mur-Artal & Tardós 2017): ``pose_rounds`` (4) rounds of
``pose_iterations`` (10) LM iterations; after each round every observation (also the ones left out) is
classified by the chi2 test on its unrobust whitened error, and only the inliers enter the next round, so
an outlier whose error falls comes back. The Huber kernel (k = ``huber_k`` sigmas, on the norm of the
whitened residual like GTSAM's ``Robust`` model) is used in every round but the last, as in ORB-SLAM2.

Parameterisation: T_cam_world is updated on the left, ``T <- [Exp(w) | v] T``, so d p_cam / d(w, v) =
[-[p_cam]x, I]. Residual rows per observation: (uL, v, uR) - measured, whitened by 1/sigma; the uR row is
zeroed for a mono observation, which makes one code path for mono and stereo.

Why numpy and not GTSAM (``python -m tests.backend.bench_ba``; numbers in docs/backend.md, "Pose-only
refinement"): a GTSAM graph with the points held by tight priors reaches the same pose and flags the same
outliers at an order of magnitude more time. The numpy cost is a few linearisations plus per-call overhead;
LM stops a round as soon as the step is < 1e-7 (rad, m) or the cost falls by < 1e-9 relative, so the rounds
after the first take few iterations.
"""

from __future__ import annotations

import numpy as np

from vslam.backend.projection import (
    MIN_DEPTH,
    chi2_thresholds,
    measurement_matrix,
    transform_points,
    whitened_sq_errors,
)
from vslam.geometry.se3 import inv_T

_BEHIND_PENALTY_PX = 1e3  # whitened error charged to a point behind the camera, so LM never "gains" by it
_STEP_TOL = 1e-7  # stop when |(w, v)| < this (rad, m): 0.5 um at 5 m, far below any measurable change
_COST_RTOL = 1e-9  # ... or when the robust cost fell by less than this fraction
_MIN_OBS = 3  # a pose needs at least 3 points


def refine_pose(
    T_world_cam: np.ndarray,
    pts_world: np.ndarray,
    uv: np.ndarray,
    ur: np.ndarray,
    camera,
    cfg,
    sigma: np.ndarray | float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """See ``vslam.backend.ba.optimize_pose``; ``sigma``: pixel std per observation (None: cfg.pixel_sigma)."""
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    pts, meas, stereo, sig, valid = _observations(pts_world, uv, ur, camera, cfg, sigma)
    n = pts.shape[0]
    inliers = np.zeros(n, dtype=bool)
    T_cw = inv_T(T_world_cam)
    P, Z, S, w = pts[valid], meas[valid], stereo[valid], 1.0 / sig[valid]
    thr = chi2_thresholds(S, cfg.chi2_mono, cfg.chi2_stereo)
    active = _classify(T_cw, P, Z, S, 1.0 / w, thr, camera)
    if P.shape[0] < _MIN_OBS:
        inliers[valid] = active
        return T_world_cam.copy(), inliers
    active[:] = True  # round 1 uses every observation, as in ORB-SLAM2
    for rnd in range(cfg.pose_rounds):
        if active.sum() < _MIN_OBS:
            break
        k = cfg.huber_k if rnd < cfg.pose_rounds - 1 else None
        T_cw = _levenberg_marquardt(T_cw, P[active], Z[active], S[active], w[active], camera, k, cfg.pose_iterations)
        active = _classify(T_cw, P, Z, S, 1.0 / w, thr, camera)
    inliers[valid] = active
    return inv_T(T_cw), inliers


def pose_covariance(
    T_world_cam: np.ndarray,
    pts_world: np.ndarray,
    uv: np.ndarray,
    ur: np.ndarray,
    camera,
    cfg,
    sigma: np.ndarray | float | None = None,
) -> np.ndarray:
    """(6,6) first-order covariance (J^T J)^-1 of a refined pose from its inlier observations.

    Same arguments as ``refine_pose`` (pass the inliers only). Order (w, v) of the left perturbation
    T_cam_world <- [Exp(w) | v] T_cam_world: rotation rad, translation m, camera axes; the camera centre
    moves by -R_cw^T v, so sqrt(tr Sigma_vv) is its position std in metres. Residuals are whitened by the
    pixel sigma, so this assumes exact map points: a lower bound that still grows with few, clustered or
    depth-less observations. All-inf when fewer than 3 usable observations or the system is singular.
    """
    pts, meas, stereo, sig, valid = _observations(pts_world, uv, ur, camera, cfg, sigma)
    unknown = np.full((6, 6), np.inf)
    if valid.sum() < _MIN_OBS:
        return unknown
    T_cw = inv_T(np.asarray(T_world_cam, dtype=np.float64))
    _, H, _ = _linearize(T_cw[:3, :3], T_cw[:3, 3], np.ascontiguousarray(pts[valid].T), np.ascontiguousarray(meas[valid].T),
                         stereo[valid].astype(np.float64), 1.0 / sig[valid], camera, None)
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return unknown
    return cov if np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0) else unknown


def _observations(pts_world, uv, ur, camera, cfg, sigma):
    """-> pts (N,3), meas (N,3), stereo (N,) bool, sigma (N,) px, valid (N,) bool: the rows a pose can use."""
    pts = np.asarray(pts_world, dtype=np.float64).reshape(-1, 3)
    meas, stereo = measurement_matrix(uv, ur)
    n = pts.shape[0]
    sig = np.broadcast_to(np.asarray(cfg.pixel_sigma if sigma is None else sigma, dtype=np.float64), (n,))
    valid = np.isfinite(pts).all(axis=1) & np.isfinite(meas[:, :2]).all(axis=1) & (sig > 0)
    if camera.baseline <= 0:
        stereo = np.zeros(n, dtype=bool)  # no baseline, no stereo residual
    return pts, meas, stereo, sig, valid


def _classify(T_cw, P, Z, S, sig, thr, camera) -> np.ndarray:
    chi2, _ = whitened_sq_errors(transform_points(T_cw, P), Z, S, sig, camera)
    return chi2 <= thr


def _levenberg_marquardt(T_cw, P, Z, S, w, camera, huber_k, iterations) -> np.ndarray:
    """LM on the robust cost; (4,4) T_cam_world in -> refined T_cam_world out."""
    PT = np.ascontiguousarray(P.T)  # (3,n): row-wise vector maths below is contiguous
    ZT = np.ascontiguousarray(Z.T)
    Sf = S.astype(np.float64)
    return lm_pose(T_cw, lambda R, t: _linearize(R, t, PT, ZT, Sf, w, camera, huber_k), iterations)


def lm_pose(T_cw: np.ndarray, linearize, iterations: int) -> np.ndarray:
    """Levenberg-Marquardt on one pose, shared by every pose-only cost (points; points + lines).

    ``linearize(R, t) -> (robust cost, H (6,6), g (6,))`` at T_cam_world = [R | t], in the left-perturbation
    order (w, v). (4,4) T_cam_world in -> refined T_cam_world out."""
    R, t = T_cw[:3, :3].copy(), T_cw[:3, 3].copy()
    cost, H, g = linearize(R, t)
    lam = 1e-5
    for _ in range(iterations):
        Hd = H + lam * np.diag(np.diag(H) + 1e-9)
        try:
            delta = -np.linalg.solve(Hd, g)
        except np.linalg.LinAlgError:
            break
        if np.linalg.norm(delta) < _STEP_TOL:
            break  # converged: the step would change nothing measurable
        dR = _so3_exp(delta[:3])
        R_new, t_new = dR @ R, dR @ t + delta[3:]
        cost_new, H_new, g_new = linearize(R_new, t_new)
        if cost_new <= cost:
            small = cost - cost_new <= _COST_RTOL * cost
            R, t, cost, H, g = R_new, t_new, cost_new, H_new, g_new
            lam = max(lam * 0.1, 1e-9)
            if small:
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _linearize(R, t, PT, ZT, S, w, camera, huber_k):
    """Robust cost, Gauss-Newton H = sum wi J^T J (6,6) and g = sum wi J^T r (6,) at T_cam_world = [R | t].

    PT: (3,n) world points; ZT: (3,n) measured uL, v, uR; S: (n,) 1.0 stereo / 0.0 mono; w: (n,) 1/sigma.
    Jacobian rows (standard pinhole form, xn = X/Z, yn = Y/Z, xb = (X - b)/Z, iz = 1/Z) w.r.t. (w, v):
    uL: fx [-xn yn, 1 + xn^2, -yn, iz, 0, -xn iz];  v: fy [-(1 + yn^2), xn yn, xn, 0, iz, -yn iz];
    uR: fx [-xb yn, 1 + xb xn, -yn, iz, 0, -xb iz]; with ``camera.disparity_sigma`` > 0 the third row is the
    disparity fx b / Z instead (uL row minus uR row), whitened by 1 / disparity_sigma.
    """
    fx, fy = camera.fx, camera.fy
    pc = R @ PT + t[:, None]
    Zc = pc[2]
    front = Zc > MIN_DEPTH
    iz = 1.0 / np.where(front, Zc, 1.0)
    xn, yn = pc[0] * iz, pc[1] * iz
    xb = xn - camera.baseline * iz
    ru = (fx * xn + camera.cx - ZT[0]) * w
    rv = (fy * yn + camera.cy - ZT[1]) * w
    sd = float(camera.disparity_sigma)
    if sd > 0:  # third row: disparity error fx b / Z - (uL - uR), whitened by its own sigma (RGB-D)
        rr = (fx * (xn - xb) - (ZT[0] - ZT[2])) * (S / sd)
    else:
        rr = (fx * xb + camera.cx - ZT[2]) * (w * S)
    e2 = ru * ru + rv * rv + rr * rr
    e2 = np.where(front, e2, _BEHIND_PENALTY_PX**2)
    if huber_k is None:
        sw = front.astype(np.float64)
        cost = 0.5 * float(e2.sum())
    else:
        e = np.sqrt(e2)
        big = e > huber_k
        sw = np.sqrt(np.where(big, huber_k / np.where(big, e, 1.0), 1.0)) * front  # sqrt of the IRLS weight
        cost = float(np.sum(np.where(big, huber_k * (e - 0.5 * huber_k), 0.5 * e2)))
    n = PT.shape[1]
    a, b = fx * w * sw, fy * w * sw
    c = a * S if sd <= 0 else fx * sw * S / sd
    J = np.empty((6, 3, n))
    xy = xn * yn
    # J[column, row]: columns (w, v), rows (uL, v, uR); the formulas are in the docstring
    J[0, 0], J[1, 0], J[2, 0] = -a * xy, a * (1.0 + xn * xn), -a * yn
    J[3, 0], J[4, 0], J[5, 0] = a * iz, 0.0, -a * xn * iz
    J[0, 1], J[1, 1], J[2, 1] = -b * (1.0 + yn * yn), b * xy, b * xn
    J[3, 1], J[4, 1], J[5, 1] = 0.0, b * iz, -b * yn * iz
    if sd > 0:  # d(fx b / Z) = uL row - uR row: fx b iz [-yn, xn, 0, 0, 0, -iz]
        cb = c * camera.baseline * iz
        J[0, 2], J[1, 2], J[2, 2] = -cb * yn, cb * xn, 0.0
        J[3, 2], J[4, 2], J[5, 2] = 0.0, 0.0, -cb * iz
    else:
        J[0, 2], J[1, 2], J[2, 2] = -c * xb * yn, c * (1.0 + xb * xn), -c * yn
        J[3, 2], J[4, 2], J[5, 2] = c * iz, 0.0, -c * xb * iz
    J = J.reshape(6, 3 * n)
    r = np.concatenate([ru * sw, rv * sw, rr * sw])
    return cost, J @ J.T, J @ r


def _so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (3,) rotation vector (rad) -> (3,3); a hand-rolled scipy-free version (called every iteration)."""
    th2 = float(w @ w)
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th2 < 1e-16:
        return np.eye(3) + K + 0.5 * K @ K
    th = np.sqrt(th2)
    return np.eye(3) + (np.sin(th) / th) * K + ((1.0 - np.cos(th)) / th2) * K @ K
