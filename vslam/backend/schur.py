"""Local BA's Levenberg-Marquardt in numpy: the points eliminated by the Schur complement, vectorised.

The same robust cost as GTSAM's graph of ``factors.FactorBuilder`` (stereo-like pinhole of ``projection``, Huber
on the whitened residual norm, RGB-D disparity rows) and the same LM settings as ``factors.lm_params``
(lambda starts at 1 and follows Nielsen's rule, stop on a relative cost decrease below 1e-6), so it reaches
the same minimum; the path differs in rounding and in the pose retraction (``T_cam_world <- [Exp(w) | v]
T_cam_world``, as ``pose_only``; GTSAM retracts T_world_cam on the right), so estimates agree to the LM
tolerance, not bit for bit. Held poses are constants here, not variables with a tight prior.

Why (``BackendConfig.solver``): a local BA window has few free poses (<= ``ba_window``) and thousands of points
with two or three observations each. GTSAM eliminates the points one clique at a time and LM re-adds one damping
factor per variable on every try, and each factor is built from Python (timings on TUM teddy windows:
docs/backend.md, "Local BA timings"). Here the reduced camera system is dense (6 x free poses) and built with a
few array products. ``python -m tests.backend.bench_ba`` and ``tests/backend/test_schur.py`` compare the two.
"""

from __future__ import annotations

import numpy as np

from vslam.backend.projection import MIN_DEPTH
from vslam.geometry.se3 import gather_Rt, so3_exp

_REL_TOL = 1e-6  # factors.lm_params: relative error decrease that ends LM
_ABS_TOL = 1e-10
_MIN_FIDELITY = 1e-3  # GTSAM's minModelFidelity: a step is taken when it achieves this much of the predicted gain
_MAX_LAMBDA = 1e5  # GTSAM's lambdaUpperBound


def schur_lm(Tcw: np.ndarray, P: np.ndarray, ik: np.ndarray, ip: np.ndarray, meas: np.ndarray, stereo: np.ndarray,
             sigma: np.ndarray, free: np.ndarray, camera, huber_k: float, iterations: int) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Robust LM over the poses with ``free`` and every point that has an observation.

    Tcw (K,4,4) T_cam_world; P (N,3) world points; ik, ip (M,) pose / point index of each observation; meas (M,3)
    (uL, v, uR); stereo (M,) bool; sigma (M,) px; free (K,) bool. -> (Tcw, P, LM iterations, robust cost at the
    start). Points without observations and held poses come back unchanged."""
    Tcw, P = Tcw.copy(), P.copy()
    prob = _Problem(ik, ip, meas, stereo, sigma, free, camera, huber_k, P.shape[0])
    lin = prob.linearize(Tcw, P)
    cost0 = lin.cost
    lam, nu = 1.0, 2.0
    it = 0
    while it < iterations:
        it += 1
        accepted = False
        while True:
            step = prob.solve(lin, lam)
            if step is None:  # singular even with damping
                lam *= nu
                nu *= 2.0
                if lam > _MAX_LAMBDA:
                    break
                continue
            dp, dl, predicted = step
            Tn, Pn = _retract(Tcw, P, dp, dl, prob.free_idx)
            cost_new = prob.cost(Tn, Pn)
            gain = lin.cost - cost_new
            if predicted > 0 and gain / predicted > _MIN_FIDELITY:
                rho = gain / predicted
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                old = lin.cost
                Tcw, P = Tn, Pn
                lin = prob.linearize(Tcw, P)
                accepted = True
                break
            lam *= nu
            nu *= 2.0
            if lam > _MAX_LAMBDA:
                break
        if not accepted or old - lin.cost <= max(_REL_TOL * old, _ABS_TOL):
            break
    return Tcw, P, it, cost0


def robust_cost(Tcw, P, ik, ip, meas, stereo, sigma, camera, huber_k: float) -> float:
    """The robust cost ``schur_lm`` minimises, at Tcw (K,4,4) T_cam_world and P (N,3) (arguments as there)."""
    free = np.zeros(Tcw.shape[0], bool)
    return _Problem(ik, ip, meas, stereo, sigma, free, camera, huber_k, P.shape[0]).cost(Tcw, P)


def _retract(Tcw, P, dp, dl, free_idx):
    Tn, Pn = Tcw.copy(), P + dl
    for n, k in enumerate(free_idx.tolist()):
        w, v = dp[6 * n:6 * n + 3], dp[6 * n + 3:6 * n + 6]
        dR = so3_exp(w)
        Tn[k, :3, :3] = dR @ Tcw[k, :3, :3]
        Tn[k, :3, 3] = dR @ Tcw[k, :3, 3] + v
    return Tn, Pn


class _Lin:
    __slots__ = ("cost", "Jp", "Jl", "r")

    def __init__(self, cost, Jp, Jl, r):
        self.cost, self.Jp, self.Jl, self.r = cost, Jp, Jl, r


class _Problem:
    """Observation arrays and the per-iteration algebra (residuals, Jacobians, reduced system)."""

    def __init__(self, ik, ip, meas, stereo, sigma, free, camera, huber_k, n_points):
        o = np.argsort(ip, kind="stable")  # observations sorted by point: a point's sums are one reduceat
        ik, ip, meas, stereo, sigma = ik[o], ip[o], meas[o], stereo[o], sigma[o]
        self.ik, self.ip, self.meas = ik, ip, meas
        self.S = stereo.astype(np.float64)
        self.w = 1.0 / sigma
        self.cam, self.k = camera, huber_k
        self.sd = float(camera.disparity_sigma)
        self.free_idx = np.flatnonzero(free)
        self.n_points, self.n_free = n_points, self.free_idx.size
        # observed points, renumbered 0..Nu-1; sums over a point's (a free pose's) observations by reduceat
        self.pts, self.lp = np.unique(ip, return_inverse=True)
        self.pt_starts = np.flatnonzero(np.r_[True, np.diff(self.lp) != 0])
        slot = np.full(free.shape[0], -1, np.int64)
        slot[self.free_idx] = np.arange(self.n_free)
        fi = slot[ik]
        self.m_free = np.flatnonzero(fi >= 0)
        self.f = fi[self.m_free]
        order = np.argsort(self.f, kind="stable")
        self.by_pose, fs = self.m_free[order], self.f[order]
        self.pose_starts = np.flatnonzero(np.r_[True, fs[1:] != fs[:-1]]) if fs.size else np.zeros(0, np.int64)
        self.pose_slots = fs[self.pose_starts]
        pairs = self.lp[self.m_free] * max(self.n_free, 1) + self.f
        self.unique_pairs = np.unique(pairs).size == pairs.size  # a point seen once per keyframe (the map's rule)
        # the GTSAM factors' error behind the camera: 2 fx per row, whitened, with a zero Jacobian
        self.behind = 2.0 * camera.fx * self.w

    def _residuals(self, Tcw, P):
        R, t = gather_Rt(Tcw, self.ik)
        pc = np.einsum("mij,mj->mi", R, P[self.ip]) + t
        Z = pc[:, 2]
        front = Z > MIN_DEPTH
        iz = 1.0 / np.where(front, Z, 1.0)
        xn, yn = pc[:, 0] * iz, pc[:, 1] * iz
        c = self.cam
        w, S = self.w, self.S
        r = np.empty((len(Z), 3))
        r[:, 0] = (c.fx * xn + c.cx - self.meas[:, 0]) * w
        r[:, 1] = (c.fy * yn + c.cy - self.meas[:, 1]) * w
        if self.sd > 0:
            r[:, 2] = (c.fx * c.baseline * iz - (self.meas[:, 0] - self.meas[:, 2])) * (S / self.sd)
        else:
            r[:, 2] = (c.fx * (xn - c.baseline * iz) + c.cx - self.meas[:, 2]) * (w * S)
        back = ~front
        if back.any():
            r[back] = self.behind[back, None] * np.c_[np.ones(back.sum()), np.ones(back.sum()), S[back]]
        return r, pc, R, iz, xn, yn, front

    def _robust(self, r):
        e2 = np.einsum("mi,mi->m", r, r)
        e = np.sqrt(e2)
        big = e > self.k
        cost = float(np.sum(np.where(big, self.k * (e - 0.5 * self.k), 0.5 * e2)))
        sw = np.sqrt(np.where(big, self.k / np.where(big, e, 1.0), 1.0))  # sqrt of the IRLS weight (GTSAM Robust)
        return cost, sw

    def cost(self, Tcw, P) -> float:
        return self._robust(self._residuals(Tcw, P)[0])[0]

    def linearize(self, Tcw, P) -> _Lin:
        r, pc, R, iz, xn, yn, front = self._residuals(Tcw, P)
        cost, sw = self._robust(r)
        c = self.cam
        a = c.fx * self.w * sw * front
        b = c.fy * self.w * sw * front
        D = np.zeros((len(iz), 3, 3))  # d (whitened, weighted) residual / d point in the camera frame
        D[:, 0, 0], D[:, 0, 2] = a * iz, -a * xn * iz
        D[:, 1, 1], D[:, 1, 2] = b * iz, -b * yn * iz
        if self.sd > 0:
            D[:, 2, 2] = -(c.fx * c.baseline / self.sd) * self.S * sw * front * iz * iz
        else:
            s = a * self.S
            D[:, 2, 0], D[:, 2, 2] = s * iz, -s * (xn - c.baseline * iz) * iz
        Jp = np.empty((len(iz), 3, 6))
        # row d: d^T (-[pc]x) = (pc x d)^T; np.cross's formulas written out (same values, faster)
        a0, a1, a2 = pc[:, None, 0], pc[:, None, 1], pc[:, None, 2]
        d0, d1, d2 = D[:, :, 0], D[:, :, 1], D[:, :, 2]
        Jp[:, :, 0] = a1 * d2 - a2 * d1
        Jp[:, :, 1] = a2 * d0 - a0 * d2
        Jp[:, :, 2] = a0 * d1 - a1 * d0
        Jp[:, :, 3:] = D
        Jl = D @ R
        return _Lin(cost, Jp, Jl, r * sw[:, None])

    def solve(self, lin: _Lin, lam: float):
        """Damped normal equations, points eliminated -> (pose step (6F,), point step (N,3), predicted gain) or None."""
        F = self.n_free
        Jp, Jl, r = lin.Jp, lin.Jl, lin.r
        JlT = Jl.transpose(0, 2, 1)
        V = np.add.reduceat(JlT @ Jl, self.pt_starts)  # (Nu,3,3)
        gl = np.add.reduceat((JlT @ r[:, :, None])[:, :, 0], self.pt_starts)
        V[:, [0, 1, 2], [0, 1, 2]] += lam
        Vinv = _inv3(V)
        if Vinv is None:
            return None
        dp = np.zeros(6 * F)
        m, f = self.m_free, self.f
        if m.size:
            JpT = Jp.transpose(0, 2, 1)
            o = self.by_pose
            U = np.zeros((F, 6, 6))
            U[self.pose_slots] = np.add.reduceat(JpT[o] @ Jp[o], self.pose_starts)
            gp = np.zeros((F, 6))
            gp[self.pose_slots] = np.add.reduceat((JpT[o] @ r[o, :, None])[:, :, 0], self.pose_starts)
            # W (6F x 3Nu) dense over the few free poses, stored pose-major: the Schur products become GEMMs
            Nu = V.shape[0]
            W4, Y4 = np.zeros((F, 6, Nu, 3)), np.zeros((F, 6, Nu, 3))
            Wm = JpT[m] @ Jl[m]
            lpm = self.lp[m]
            if self.unique_pairs:  # Y = W V^-1 per observation, then placed like W
                W4[f, :, lpm, :] = Wm
                Y4[f, :, lpm, :] = Wm @ Vinv[lpm]
            else:
                np.add.at(W4, (f, slice(None), lpm, slice(None)), Wm)
                np.add.at(Y4, (f, slice(None), lpm, slice(None)), Wm @ Vinv[lpm])
            W, Y = W4.reshape(6 * F, 3 * Nu), Y4.reshape(6 * F, 3 * Nu)
            Sred = _block_diag(U) - Y @ W.T  # U - sum_p W_p V_p^-1 W_p^T
            Sred[np.arange(6 * F), np.arange(6 * F)] += lam
            rhs = -(gp.reshape(-1) - Y @ gl.reshape(-1))
            try:
                dp = np.linalg.solve(Sred, rhs)
            except np.linalg.LinAlgError:
                return None
            if not np.all(np.isfinite(dp)):
                return None
            glw = gl + (dp @ W).reshape(Nu, 3)
        else:
            glw = gl
        dlu = -(Vinv @ glw[:, :, None])[:, :, 0]
        dl = np.zeros((self.n_points, 3))
        dl[self.pts] = dlu
        # predicted gain of the undamped linear model, 0.5|r|^2 - 0.5|J d + r|^2 = -g.d - 0.5 d'H d, where
        # (H + lam I) d = -g makes d'H d = -g.d - lam |d|^2
        gd = float(gp.reshape(-1) @ dp) if m.size else 0.0
        gd += float(np.einsum("pa,pa->", gl, dlu))
        predicted = 0.5 * (lam * (float(dp @ dp) + float(np.einsum("pa,pa->", dlu, dlu))) - gd)
        return dp, dl, predicted


def _inv3(V: np.ndarray) -> np.ndarray | None:
    """Inverses of a stack (N,3,3) of symmetric positive definite matrices by cofactors (None if one is singular)."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, g = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    A, B, C = d * g - e * e, c * e - b * g, b * e - c * d
    det = a * A + b * B + c * C
    if not np.all(det > 0):
        return None
    D, E, G = a * g - c * c, b * c - a * e, a * d - b * b
    out = np.empty_like(V)
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = A, B, C
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = B, D, E
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = C, E, G
    return out / det[:, None, None]


def _block_diag(blocks: np.ndarray) -> np.ndarray:
    """(F,6,6) -> (6F,6F) block-diagonal matrix."""
    F = blocks.shape[0]
    out = np.zeros((F, 6, F, 6))
    out[np.arange(F), :, np.arange(F), :] = blocks
    return out.reshape(6 * F, 6 * F)
