"""Line reprojection factor for GTSAM: a Plücker line in orthonormal form seen from keyframe poses.

GTSAM has no line Value, so a line j is stored as two standard Values: ``LU(j)`` a ``Rot3`` (the U of the
orthonormal form) and ``LW(j)`` a ``Rot2`` (W), see :mod:`vslam.geometry.plucker`. Their retractions
(U Exp(theta), W Rot(phi)) are exactly the 4-DoF orthonormal update of Bartoli & Sturm (2005), so LM, iSAM2
and Marginals work on it unchanged, and the line can never leave the Plücker quadric.

Residual per observation: the signed pixel distances of the observed segment's two end points to the
projected infinite line ``l = K_L n_c`` (``plucker.project``); whitened by ``sigma`` px and passed through a
Huber kernel *per observation* the way ``noiseModel.Robust`` applies it (error rho, IRLS linearisation; see
``_huber``), so the factor's error is the Huber cost of every observation even though one factor holds many.

Why one ``CustomFactor`` per *line* (all its observations) instead of per observation: the Python callback
is the cost (DEPENDENCIES.md: an analytic linearize in Python costs many times a C++ projection factor), and
one callback per line amortises it over the observations while keeping the graph structure of the
per-observation form (a line touches only the poses that see it): a callback costs about the same for one
observation as for six (docs/lines.md). Local BA does not use this factor by default:
``line_window`` puts every line of a window into one callback (``backend.line_ba``).

Jacobians (analytic). The pose is ``Pose3 = T_world_cam`` with GTSAM's right retraction T Exp(omega, v), so
T_cam_world <- Exp(-xi) T_cam_world and, to first order, n_c <- n_c + [n_c]x omega + [d_c]x v.
The line: L_w = (w1 u1, w2 u2), dL_w/d(theta, phi) from ``plucker.orthonormal_jacobian``, and
n_c = R_cw n_w + [t_cw]x R_cw d_w.
"""

from __future__ import annotations

import gtsam
import numpy as np

from vslam.geometry import plucker as pl
from vslam.geometry.se3 import skew


def LU(j: int) -> int:
    """Key of line j's U (Rot3)."""
    return gtsam.symbol("u", j)


def LW(j: int) -> int:
    """Key of line j's W (Rot2)."""
    return gtsam.symbol("w", j)


def _skew_stack(v: np.ndarray) -> np.ndarray:
    """(n,3) -> (n,3,3) cross-product matrices."""
    return (v @ _SKEW_BASIS).reshape(-1, 3, 3)


#: [v]x = sum_i v_i [e_i]x: a (3,9) matmul builds the flattened stack in one call.
_SKEW_BASIS = np.stack([skew(e).reshape(9) for e in np.eye(3)])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis with broadcasting; np.cross's fixed cost per call dominates on small
    arrays (docs/speed.md)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _huber(e: np.ndarray, k: float, jac: bool) -> tuple[np.ndarray, np.ndarray]:
    """Huber on the norm a = |e| of each whitened (2,) row of e (n,2), as GTSAM's ``noiseModel.Robust``
    does it: the *error* is rho(a) (returned residual sqrt(2 rho(a)) e / a, so |r|^2 / 2 = rho), while the
    *linearisation* is IRLS, residual and Jacobian scaled by sqrt(w(a)) = sqrt(min(1, k / a)).
    -> (residual (n,2), sqrt_w (n,)); the residual is the IRLS one when ``jac`` (what LM's linear model
    needs), the rho one otherwise (what LM compares). The square-rooted rho residual with its exact
    derivative was tried first: its Gauss-Newton step overshoots by 2x for a > k and stalled LM.
    """
    a = np.linalg.norm(e, axis=1)
    big = a > k
    safe = np.where(big, a, 1.0)
    sw = np.where(big, np.sqrt(k / safe), 1.0)
    if jac:
        return e * sw[:, None], sw
    s = np.where(big, np.sqrt(np.maximum(2.0 * k * safe - k * k, 0.0)) / safe, 1.0)
    return e * s[:, None], sw


def line_factor(
    line_id: int, kf_ids: list[int], segs: np.ndarray, K_L: np.ndarray, sigma: float, huber_k: float | None
) -> gtsam.CustomFactor:
    """One CustomFactor on [LU(j), LW(j), X(k1), ..., X(kn)]: all observations of line j.

    segs: (n,4) observed segments (ideal pixels) in keyframes kf_ids (n,); sigma: pixel std; huber_k:
    Huber threshold in sigmas (None: plain least squares). Residual (2n,), whitened inside (unit noise model).
    """
    from gtsam.symbol_shorthand import X

    segs = np.ascontiguousarray(segs, dtype=np.float64).reshape(-1, 4)
    n = len(segs)
    keys = [LU(line_id), LW(line_id)] + [X(int(k)) for k in kf_ids]
    inv_sigma = 1.0 / float(sigma)
    model = gtsam.noiseModel.Unit.Create(2 * n)

    x = np.ones((n, 2, 3))
    x[:, 0, :2], x[:, 1, :2] = segs[:, :2], segs[:, 2:]
    pose_keys = keys[2:]
    rows = np.arange(n)

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
        # World-frame form (fewer numpy calls; their fixed cost dominates at this size):
        # n_c = R^T (n_w - C x d_w), d_c = R^T d_w for T_world_cam = [R | C].
        U = v.atRot3(keys[0]).matrix()
        th = v.atRot2(keys[1]).theta()
        w = (np.cos(th), np.sin(th))
        nw, dw = w[0] * U[:, 0], w[1] * U[:, 1]
        Twc = np.array([v.atPose3(k).matrix() for k in pose_keys])
        R, C = Twc[:, :3, :3], Twc[:, :3, 3]
        Rt = R.transpose(0, 2, 1)
        nc = (Rt @ (nw - C @ skew(dw))[:, :, None])[:, :, 0]  # C x d = C @ [d]x as a row product
        l = nc @ K_L.T
        rho2 = l[:, 0] ** 2 + l[:, 1] ** 2
        rho = np.sqrt(rho2)
        xl = (x @ l[:, :, None])[:, :, 0]  # (n,2)
        e = xl * (inv_sigma / rho)[:, None]
        if huber_k is not None:
            r, sw = _huber(e, huber_k, H is not None)
        else:
            r, sw = e, None
        if H is None:
            return r.reshape(-1)
        # de/dl = x / rho - (x . l) (l0, l1, 0) / rho^3, then dl/dn_c = K_L
        l01 = l.copy()
        l01[:, 2] = 0.0
        G = (x / rho[:, None, None] - (xl / (rho2 * rho)[:, None])[:, :, None] * l01[:, None, :]) @ (K_L * inv_sigma)
        if sw is not None:  # IRLS: the Jacobian is scaled like the residual
            G = sw[:, None, None] * G
        # line: dn_c/d(n_w, d_w) = R^T [I, -[C]x]
        GR = G @ Rt
        J_line = np.concatenate([GR, -GR @ _skew_stack(C)], axis=2).reshape(2 * n, 6) @ pl.orthonormal_jacobian(U, np.array(w))
        H[0] = np.ascontiguousarray(J_line[:, :3])
        H[1] = np.ascontiguousarray(J_line[:, 3:])
        # pose (right retraction): dn_c/d(omega, v) = [[n_c]x, [d_c]x]
        dc = dw @ R
        Jp = G @ np.concatenate([_skew_stack(nc), _skew_stack(dc)], axis=2)  # (n,2,6)
        Hp = np.zeros((n, 2 * n, 6))
        Hp[rows, 2 * rows] = Jp[:, 0]
        Hp[rows, 2 * rows + 1] = Jp[:, 1]
        for i in range(n):
            H[2 + i] = Hp[i]
        return r.reshape(-1)

    return gtsam.CustomFactor(model, keys, error)


def insert_line(values: gtsam.Values, line_id: int, L_world: np.ndarray) -> None:
    """Put Plücker L (6,) into ``values`` as LU(j) (Rot3) and LW(j) (Rot2)."""
    U, w = pl.to_orthonormal(L_world)
    values.insert(LU(line_id), gtsam.Rot3(U))
    values.insert(LW(line_id), gtsam.Rot2(float(np.arctan2(w[1], w[0]))))


def line_from_values(values: gtsam.Values, line_id: int) -> np.ndarray:
    """Plücker (6,) of line j in ``values``, normalised to |d| = 1."""
    th = values.atRot2(LW(line_id)).theta()
    return pl.normalize(pl.from_orthonormal(values.atRot3(LU(line_id)).matrix(), np.array([np.cos(th), np.sin(th)])))


def line_priors(line_id: int, L_world: np.ndarray, sigma_rad: float) -> list[gtsam.NonlinearFactor]:
    """Weak priors on U and W at L: keep a line seen from nearly one viewpoint well posed (4 DoF need
    two non-degenerate views) without pulling a well-observed one (pixel residuals are ~1e3 times stiffer)."""
    U, w = pl.to_orthonormal(L_world)
    return [
        gtsam.PriorFactorRot3(LU(line_id), gtsam.Rot3(U), gtsam.noiseModel.Isotropic.Sigma(3, sigma_rad)),
        gtsam.PriorFactorRot2(LW(line_id), gtsam.Rot2(float(np.arctan2(w[1], w[0]))),
                              gtsam.noiseModel.Isotropic.Sigma(1, sigma_rad)),
    ]

