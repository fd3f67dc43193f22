"""All line observations of a BA window as ONE structureless GTSAM factor on the window's poses.

Why: a Python ``CustomFactor`` per line pays Python's call overhead on every one of LM's many calls per local
BA: with one factor per line (``line_factor``) a window with lines was several times slower than its points
alone, and many times slower where lines outnumber points (``python -m tests.backend.bench_lines``, CPU time).
Here every line of the window is handled in one vectorised numpy callback, and the lines are not GTSAM
variables at all (like GTSAM's smart factors); the same window then costs little more than its points alone
(docs/lines.md, "the window factor's cost").

1. *Lines at the poses*: at the first evaluation each line's 4-DoF orthonormal form (``plucker``) gets
   ``_PRIME_ITERATIONS`` (2) Levenberg-Marquardt steps on its Huber (IRLS) end-point distances at the initial
   poses, batched over lines, with a per-line damping and a 0.05 rad trust region. After that, the lines at the
   poses LM evaluates are back-substituted in the system of the last *linearisation*,
   dl = -S^+ (J_l^T r + J_l^T J_x dx) with dx the poses' steps from there: the line part of the joint
   Gauss-Newton step whose pose part LM took (a Schur-complement solver's back-substitution), clipped to
   0.05 rad and kept per line only where it lowers that line's cost. So error() depends on the poses only
   between two linearisations, as LM assumes; it reports the cost |r| of those lines, and linearize() builds
   the reduced system at them (2.) and re-anchors. A fresh LM step per line at every evaluation (the first
   design) reached the same estimates at several times the cost per evaluation (docs/lines.md).
2. *Schur complement*: with J_l (k n x 4) the line Jacobian of a line seen n times (k rows per observation) and
   J_x its pose Jacobian, eliminating the line leaves J_x^T P J_x and J_x^T P r on the poses, P the projector
   onto the left null space of J_l (the rows Q^T J_x, Q^T r of MSCKF's null-space projection, Mourikis &
   Roumeliotis 2007, give the same system). It is summed over the window's lines as
   J_x^T J_x - D^T D with D = S^-1/2 J_l^T J_x (S = J_l^T J_l, 4 x 4 per line) and handed to GTSAM as 6K
   rows (K poses: the Cholesky factor of H + 1e-10 max(diag H) I). Poses the graph holds (a local BA's fixed
   keyframes, about two thirds of those that see its lines) are not among the K: their poses are read as constants.
   Building the k n - 4 projected rows per line with a QR per group of lines instead cost more (docs/lines.md)
   and gave GTSAM a factor of hundreds of rows.
   The reduced gradient carries -D^T S^-1/2 J_l^T r, so it is exact at lines that are not yet optimal too;
   error() is the Huber cost of the line observations. A line seen twice without depths has 4 residuals for its
   4 DoF and no pose information.

With measured end-point depths (RGB-D / stereo, ``rho``) each observation has k = 4 rows (two inverse-depth rows,
zero where not measured), so a line seen twice already constrains the poses; d rho / d(n_c, d_c) from
``plucker.inverse_depth``.
Pose Jacobian (right retraction T_world_cam Exp(omega, v)): dn_c/d(omega, v) = [[n_c]x, [d_c]x], see
``line_factor``. With ``T_body_cam`` (visual-inertial BA, whose pose variables are body poses) the camera is
T_world_body T_body_cam, and a right perturbation xi of the body pose is Ad(T_cam_body) xi of the camera's,
so the rows are J_cam Ad(T_cam_body).
"""

from __future__ import annotations

import gtsam
import numpy as np
from scipy.linalg import solve_triangular

from vslam.backend.line_factor import _cross, _huber, _skew_stack
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import gather_Rt

_MAX_STEP = 0.05  # rad, largest (theta, phi) step of a line: an LM step of ``refine_lines`` or a back-substitution
_PRIME_ITERATIONS = 2  # LM steps per line at the first evaluation; later ones are back-substituted (``_predict``)


class LineWindow:
    """Line landmarks of one BA window.

    lines: (N,6) initial Plücker lines (world); obs_line (M,) index into lines; obs_pose (M,) index into
    ``pose_keys``; segs (M,4) observed segments, ideal pixels; K_L (3,3); sigma px; huber_k in sigmas.
    After optimisation ``lines()`` holds the refined lines (|d| = 1).
    """

    def __init__(self, lines: np.ndarray, obs_line: np.ndarray, obs_pose: np.ndarray, segs: np.ndarray,
                 pose_keys: list[int], K_L: np.ndarray, sigma: float, huber_k: float | None,
                 T_body_cam: np.ndarray | None = None, rho: np.ndarray | None = None, depth_weight: float = 0.0,
                 held: frozenset[int] | set[int] = frozenset()):
        self.n_lines = len(lines)
        self.line_ids: list[int] = list(range(self.n_lines))  # caller's ids of the rows of ``lines()``
        self.U, self.w = pl.to_orthonormal(np.asarray(lines, dtype=np.float64).reshape(-1, 6))
        order = np.lexsort((obs_pose, obs_line))  # observations grouped by line
        self.ol = np.asarray(obs_line, dtype=np.int64)[order]
        self.op = np.asarray(obs_pose, dtype=np.int64)[order]
        segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)[order]
        self.order = order
        m = len(self.ol)
        self.x = np.ones((m, 2, 3))
        self.x[:, 0, :2], self.x[:, 1, :2] = segs[:, :2], segs[:, 2:]
        self.pose_keys = list(pose_keys)
        self.K_L, self.inv_sigma, self.huber_k = K_L, 1.0 / sigma, huber_k
        # RGB-D / stereo end-point inverse depths (M,2) (NaN: none) and the rays they were measured along; k residual
        # rows per observation: 2 end-point distances, + 2 inverse depths (zero rows where not measured)
        self.rho_obs, self.rays, self.depth_weight, self.k = None, None, 0.0, 2
        if rho is not None and depth_weight > 0:
            self.rho_obs = np.asarray(rho, dtype=np.float64).reshape(-1, 2)[order]
            self.has_rho = np.isfinite(self.rho_obs)
            self.rays = pl.end_rays(segs, K_L)
            self.depth_weight, self.k = float(depth_weight), 4
        self.count = np.bincount(self.ol, minlength=self.n_lines)
        # a line has pose information once its k n rows exceed its 4 DoF
        self.min_views = 3 if self.k == 2 else 2
        self.starts = np.r_[0, np.cumsum(self.count)[:-1]]  # first observation row of each line (every line has >= 1)
        self.informative = self.count[self.ol] >= self.min_views  # (M,) observations of such lines
        # rank bound of the lines' information on the poses (k n - 4 per line); the factor has 6K rows when > 0
        self.dim = int(np.sum(np.maximum(self.k * self.count[self.count >= self.min_views] - 4, 0)))
        # the factor's variables: the poses the graph does not hold (``held`` keys: fixed keyframes, held by a
        # tight prior; their columns would only carry constants). Their position among them, -1 for held ones.
        self.free = np.array([i for i, k in enumerate(self.pose_keys) if k not in held], dtype=np.int64)
        self._free_pos = np.full(len(self.pose_keys), -1, np.int64)
        self._free_pos[self.free] = np.arange(len(self.free))
        self.rows = 6 * len(self.free)
        # the informative observations of free poses sorted by pose, and each pose's rows among them (``_reduced``)
        inf = np.flatnonzero(self.informative & (self._free_pos[self.op] >= 0))
        self._pose_order = inf[np.argsort(self.op[inf], kind="stable")]
        ops = self.op[self._pose_order]
        lo, hi = np.searchsorted(ops, np.unique(ops)), np.searchsorted(ops, np.unique(ops), "right")
        self._pose_runs = [(int(self._free_pos[ops[a]]), self.k * int(a), self.k * int(b)) for a, b in zip(lo, hi)]
        self._primed = False
        self._memo: tuple | None = None  # (poses bytes, linearisation, anchor U, w, lines there): ``lines_at``
        self._lin: tuple | None = None  # (poses, U, w, S^+, g_l, J_l^T J_x) of the last ``_reduced``: ``_predict``
        self.T_bc = None if T_body_cam is None else np.asarray(T_body_cam, dtype=np.float64)
        # a right perturbation of the body pose is Ad(T_cam_body) of the camera's ((omega, v) order, as GTSAM's)
        self._ad_cb = None if self.T_bc is None else gtsam.Pose3(np.linalg.inv(self.T_bc)).AdjointMap()

    def camera_poses(self, v: gtsam.Values) -> np.ndarray:
        """(K,4,4) T_world_cam of the window's pose keys in ``v`` (body poses carried through T_body_cam)."""
        T = np.array([v.atPose3(k).matrix() for k in self.pose_keys]).reshape(-1, 4, 4)
        return T if self.T_bc is None else T @ self.T_bc

    # -- numpy core ------------------------------------------------------------------------------------------
    def _geom(self, Twc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per observation: R_world_cam (M,3,3) and camera centre C (M,3)."""
        return gather_Rt(Twc, self.op)

    def _residuals(self, geom: tuple[np.ndarray, np.ndarray], U: np.ndarray, w: np.ndarray, jac: bool,
                   pose_jac: bool = True):
        """Robust whitened residuals (M,k) and, with jac, dr/d(line 4) (M,k,4) and dr/d(pose 6) (M,k,6) (None
        without ``pose_jac``: the inner line solve needs none).

        Batched matmuls and component cross products over the M observations: on these small per-observation
        matrices numpy 2's matmul costs a fraction of the same einsum (docs/speed.md).
        """
        R, C = geom
        wo = w[self.ol]
        w0, w1 = wo[:, :1], wo[:, 1:]
        # the line's basis and the camera centre in camera axes: R^T (a x b) = (R^T a) x (R^T b), so
        # n_c = R^T (n_w - C x d_w) = w0 u1c - C_c x (w1 u2c) and d_c = w1 u2c
        Uc = R.transpose(0, 2, 1) @ U[self.ol]
        Cc = np.einsum("mji,mj->mi", R, C)
        u1, u2, u3 = Uc[:, :, 0], Uc[:, :, 1], Uc[:, :, 2]
        dc = w1 * u2
        nc = w0 * u1 - _cross(Cc, dc)
        l = nc @ self.K_L.T
        rho2 = l[:, 0] ** 2 + l[:, 1] ** 2
        rho = np.sqrt(rho2)
        xl = np.einsum("mkj,mj->mk", self.x, l)
        e = xl * (self.inv_sigma / rho)[:, None]
        if self.k == 4:  # e_d = w_d (rho_obs - rho(n_c, d_c)), see plucker.inverse_depth
            r_pred, g_n, g_d = pl.inverse_depth(nc, dc, self.rays, jac)
            e = np.concatenate([e, np.where(self.has_rho, self.depth_weight * (self.rho_obs - r_pred), 0.0)], axis=1)
        r, sw = e, None
        if self.huber_k is not None:
            r, sw = _huber(e, self.huber_k, jac)
        if not jac:
            return r, None, None
        m, k = len(self.ol), self.k
        l01 = l.copy()
        l01[:, 2] = 0.0
        A = self.x / rho[:, None, None] - (xl / (rho2 * rho)[:, None])[:, :, None] * l01[:, None, :]  # de/dl
        # G: de/d(n_c, d_c) (M,k,6); the distance rows do not depend on d_c
        G = np.zeros((m, k, 6))
        G[:, :2, :3] = (A.reshape(-1, 3) @ (self.K_L * self.inv_sigma)).reshape(m, 2, 3)
        if k == 4:
            hz = self.has_rho[:, :, None]
            G[:, 2:, :3] = np.where(hz, -self.depth_weight * g_n, 0.0)
            G[:, 2:, 3:] = np.where(hz, -self.depth_weight * g_d, 0.0)
        if sw is not None:  # IRLS (see line_factor._huber)
            G *= sw[:, None, None]
        # d(n_c, d_c)/d(theta, phi): plucker.orthonormal_jacobian's columns (dn_w, dd_w) in camera axes,
        # dn_c = R^T (dn_w - C x dd_w), dd_c = R^T dd_w
        z = np.zeros_like(u3)
        dd = np.stack([w1 * u3, z, -w1 * u1, w0 * u2], axis=1)  # (M,4,3): one row per parameter
        dn = np.stack([z, -w0 * u3, w0 * u2, -w1 * u1], axis=1) - _cross(Cc[:, None, :], dd)
        Jl = G @ np.concatenate([dn, dd], axis=2).transpose(0, 2, 1)
        if not pose_jac:
            return r, Jl, None
        # right perturbation (omega, v): dn_c = [n_c]x omega + [d_c]x v, dd_c = [d_c]x omega; r^T [a]x = (r x a)^T
        Gn, Gd = G[:, :, :3], G[:, :, 3:]
        Jx = np.concatenate([_cross(Gn, nc[:, None, :]) + _cross(Gd, dc[:, None, :]), _cross(Gn, dc[:, None, :])], axis=2)
        return r, Jl, Jx

    def refine_lines(self, Twc: np.ndarray, iterations: int, U: np.ndarray | None = None, w: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Levenberg-Marquardt on every line at fixed poses (batched 4x4 solves, one damping per line) from
        (U, w) (default: the stored lines); a step that raises a line's cost is not taken and that line's
        damping grows 100x. -> refined (U, w) and (N,) 2 x robust cost per line there; stores nothing."""
        U = self.U.copy() if U is None else U.copy()
        w = self.w.copy() if w is None else w.copy()
        geom = self._geom(Twc)
        r0, _, _ = self._residuals(geom, U, w, False)
        cost = np.bincount(self.ol, np.sum(r0 * r0, 1), self.n_lines)  # 2 x Huber cost per line
        lam = np.full(self.n_lines, 1e-6)
        for _ in range(iterations):
            r, Jl, _ = self._residuals(geom, U, w, True, pose_jac=False)  # IRLS-weighted
            JlT = Jl.transpose(0, 2, 1)
            H = np.add.reduceat(JlT @ Jl, self.starts, axis=0)  # rows are grouped by line
            g = np.add.reduceat((JlT @ r[:, :, None])[:, :, 0], self.starts, axis=0)
            H += (lam[:, None] * np.diagonal(H, axis1=1, axis2=2) + 1e-12)[:, :, None] * np.eye(4)
            delta = -np.linalg.solve(H, g[:, :, None])[:, :, 0]
            # trust region: at most _MAX_STEP rad per step, so a line seen from still-wrong poses early in
            # BA cannot jump into another minimum (seen: a line near-parallel to the motion flipped)
            delta *= np.minimum(1.0, _MAX_STEP / (np.linalg.norm(delta, axis=1) + 1e-300))[:, None]
            U2 = U @ _so3_exp_batch(delta[:, :3])
            c, s = np.cos(delta[:, 3]), np.sin(delta[:, 3])
            w2 = np.stack([w[:, 0] * c - w[:, 1] * s, w[:, 1] * c + w[:, 0] * s], axis=1)
            r2, _, _ = self._residuals(geom, U2, w2, False)
            cost2 = np.bincount(self.ol, np.sum(r2 * r2, 1), self.n_lines)
            better = cost2 < cost
            U[better], w[better], cost[better] = U2[better], w2[better], cost2[better]
            lam = np.where(better, np.maximum(lam * 0.1, 1e-9), lam * 100.0)  # per-line Levenberg-Marquardt
        return U, w, cost

    def lines(self) -> np.ndarray:
        """(N,6) current lines, |d| = 1."""
        L = np.concatenate([self.w[:, :1] * self.U[:, :, 0], self.w[:, 1:] * self.U[:, :, 1]], axis=1)
        return pl.normalize(L)

    def whitened_sq_errors(self, Twc: np.ndarray) -> np.ndarray:
        """(M,) unrobust chi2 of each observation (input order) at poses Twc (K,4,4) and the current lines."""
        hk, self.huber_k = self.huber_k, None
        r, _, _ = self._residuals(self._geom(Twc), self.U, self.w, False)
        self.huber_k = hk
        out = np.empty(len(r))
        out[self.order] = np.sum(r * r, 1)
        return out

    def _reduced(self, Twc: np.ndarray, U: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lines' Gauss-Newton system on the free poses, every line eliminated (module docstring, 2.) -> (r (6K,),
        J (6K, 6K)), K free poses, with J^T J = sum_lines J_x^T P J_x and J^T r = sum_lines J_x^T P r."""
        r, Jl, Jx = self._residuals(self._geom(Twc), U, w, True)
        K = len(self.free)
        JlT = Jl.transpose(0, 2, 1)
        S = np.add.reduceat(JlT @ Jl, self.starts, axis=0)  # (N,4,4) per line
        gl = np.add.reduceat((JlT @ r[:, :, None])[:, :, 0], self.starts, axis=0)
        lam, V = np.linalg.eigh(S)  # S^+ via a pseudo-inverse root S^-1/2: a degenerate line projects as its QR would
        keep = lam > 1e-12 * np.maximum(lam[:, -1:], 1e-300)
        Sm = (np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)[:, :, None] * V.transpose(0, 2, 1))  # (N,4,4)
        B = JlT @ Jx  # (M,4,6) J_l^T J_x per observation
        Sp = Sm.transpose(0, 2, 1) @ Sm  # S^+
        self._lin = (Twc, U, w, Sp, gl, B)  # for the back-substitution (``_predict``)
        Bf = np.zeros((self.n_lines, 4, K, 6))  # B of the informative lines on the free poses as (4N, 6K)
        inf = self._pose_order
        Bf[self.ol[inf], :, self._free_pos[self.op[inf]], :] = B[inf]  # a line is seen once per keyframe
        Bf = Bf.reshape(self.n_lines, 4, 6 * K)
        E = (Sp @ Bf).reshape(4 * self.n_lines, 6 * K)  # S^+ B per line
        Bf = Bf.reshape(4 * self.n_lines, 6 * K)
        H = -(Bf.T @ E)
        g = -(E.T @ gl.reshape(-1))
        Xs = Jx[self._pose_order].reshape(-1, 6)  # the diagonal pose blocks J_x^T J_x and J_x^T r, a slice per pose
        rs = r[self._pose_order].reshape(-1)
        for i, a, b in self._pose_runs:
            H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] += Xs[a:b].T @ Xs[a:b]
            g[6 * i : 6 * i + 6] += Xs[a:b].T @ rs[a:b]
        H = 0.5 * (H + H.T)
        try:  # H + eps I = L L^T -> rows L^T, residual L^-1 g (eps: 1e-10 of the largest diagonal entry)
            L = np.linalg.cholesky(H + (1e-10 * max(float(np.max(np.diag(H))), 1e-300)) * np.eye(len(H)))
            return solve_triangular(L, g, lower=True, check_finite=False), L.T
        except np.linalg.LinAlgError:  # rounding left H indefinite: its positive part, rows sqrt(l) v^T
            lh, Vh = np.linalg.eigh(H)
            ok = lh > 1e-12 * max(float(lh[-1]), 1e-300)
            sq = np.sqrt(np.where(ok, lh, 0.0))
            return np.where(ok, (Vh.T @ g) / np.where(ok, sq, 1.0), 0.0), sq[:, None] * Vh.T

    def lines_at(self, Twc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The lines at poses Twc -> (U, w, cost per line): back-substituted in the last linearisation's system
        (``_predict``), or one ``refine_lines`` step from the anchor before there is one. Remembered for one call:
        LM linearises where it has just evaluated error(), and must get the same lines without a second solve."""
        key = Twc.tobytes()
        memo = self._memo
        if memo is not None and memo[0] == key and memo[1] is self._lin and memo[2] is self.U and memo[3] is self.w:
            return memo[4]
        lin = self._lin
        out = self._predict(Twc) if lin is not None and lin[1] is self.U else self.refine_lines(Twc, 1)
        self._memo = (key, lin, self.U, self.w, out)
        return out

    def _predict(self, Twc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The lines at poses Twc by back-substitution in the last linearisation's system: dl = -S^+ (g_l +
        J_l^T J_x dx), dx the poses' steps from there (the joint Gauss-Newton step whose pose part LM took),
        per line whichever of that and the anchor line costs less. -> (U, w, cost) as ``refine_lines``."""
        T0, U, w, Sp, gl, B = self._lin
        R0T = T0[:, :3, :3].transpose(0, 2, 1)  # dx to first order: T = T0 Exp(omega, v)
        dt = (R0T @ (Twc[:, :3, 3] - T0[:, :3, 3])[:, :, None])[:, :, 0]
        dx = np.concatenate([_so3_log_batch(R0T @ Twc[:, :3, :3]), dt], axis=1)
        rhs = gl + np.add.reduceat((B @ dx[self.op][:, :, None])[:, :, 0], self.starts, axis=0)
        delta = -(Sp @ rhs[:, :, None])[:, :, 0]
        delta *= np.minimum(1.0, _MAX_STEP / (np.linalg.norm(delta, axis=1) + 1e-300))[:, None]
        U2 = U @ _so3_exp_batch(delta[:, :3])
        c, s = np.cos(delta[:, 3]), np.sin(delta[:, 3])
        w2 = np.stack([w[:, 0] * c - w[:, 1] * s, w[:, 1] * c + w[:, 0] * s], axis=1)
        geom = self._geom(Twc)
        r1, _, _ = self._residuals(geom, U, w, False)
        r2, _, _ = self._residuals(geom, U2, w2, False)
        cost1 = np.bincount(self.ol, np.sum(r1 * r1, 1), self.n_lines)
        cost2 = np.bincount(self.ol, np.sum(r2 * r2, 1), self.n_lines)
        better = cost2 < cost1
        return (np.where(better[:, None, None], U2, U), np.where(better[:, None], w2, w), np.where(better, cost2, cost1))

    # -- GTSAM glue ---------------------------------------------------------------------------------------------
    def factor(self) -> gtsam.CustomFactor | None:
        """The structureless factor on the window's poses; None when no line has ``min_views`` views."""
        if self.dim == 0 or self.rows == 0:
            return None

        def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
            # The lines follow the poses from the last *linearisation* (an accepted LM point, ``lines_at``),
            # never from a trial point, so error() is a function of the poses alone, as LM assumes.
            Twc = self.camera_poses(v)
            if not self._primed:  # first call (LM's initial error): converge the lines at the initial poses
                self.U, self.w, cost = self.refine_lines(Twc, _PRIME_ITERATIONS)
                self._memo = (Twc.tobytes(), self._lin, self.U, self.w, (self.U, self.w, cost))
                self._primed = True
            U, w, cost = self.lines_at(Twc)
            if H is None:
                # The cost of the lines as they are, |r|, not |Q^T r|: the two agree only at the exact inner
                # optimum, and the projected norm under-reports a line that is not yet there, which made LM
                # reject every step near convergence (with Huber the inner solve converges linearly).
                out = np.zeros(self.rows)
                out[0] = np.sqrt(float(cost[self.count >= self.min_views].sum()))  # the lines that have rows
                return out
            r, J = self._reduced(Twc, U, w)
            self.U, self.w = U, w  # re-anchor
            for i in range(len(self.free)):
                Ji = J[:, 6 * i : 6 * i + 6]
                H[i] = np.ascontiguousarray(Ji if self._ad_cb is None else Ji @ self._ad_cb)
            return r

        keys = [self.pose_keys[i] for i in self.free.tolist()]  # held poses are read from the values all the same
        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(self.rows), keys, error)


def _so3_exp_batch(w: np.ndarray) -> np.ndarray:
    """(N,3) rotation vectors -> (N,3,3) (Rodrigues, small-angle safe)."""
    th2 = np.sum(w * w, 1)
    th = np.sqrt(th2)
    small = th2 < 1e-16
    a = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5, (1.0 - np.cos(th)) / np.where(small, 1.0, th2))
    K = _skew_stack(w)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def _so3_log_batch(R: np.ndarray) -> np.ndarray:
    """(K,3,3) rotations of less than pi -> (K,3) rotation vectors; LM's pose steps are small (scipy's
    ``Rotation.from_matrix`` has a far larger fixed cost per call; docs/speed.md)."""
    v = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.linalg.norm(v, axis=1)  # sin(theta)
    th = np.arctan2(s, 0.5 * (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0))
    return v * np.where(s > 1e-12, th / np.where(s > 1e-12, s, 1.0), 1.0)[:, None]
