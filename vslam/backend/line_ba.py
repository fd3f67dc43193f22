"""Line landmarks in local BA: the problem type, the GTSAM terms and the chi2 classification.

``local_bundle_adjustment`` calls ``line_terms`` when ``BAProblem.lines`` is set, adds the factors and
values to its graph (both LM rounds), and reads the lines back with ``line_estimates``.

Two modes (``LineProblem.mode``): "window" (default) puts every line of the window into one structureless
factor on the poses (``line_window``: lines solved inside, Schur by null-space projection) -- one Python
callback per LM evaluation instead of one per line; "landmark" makes each line a GTSAM variable pair
(Rot3, Rot2) with one ``line_factor.line_factor`` over its observations and weak priors (``prior_sigma_rad``).
Both minimise the same cost; "landmark" is kept for iSAM2/marginals users and as the reference in tests.
Measured (``python -m tests.backend.bench_lines``): see ``tests/backend/bench_lines.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from gtsam.symbol_shorthand import X

from vslam.backend import line_factor as lf
from vslam.backend.line_window import LineWindow
from vslam.geometry import plucker as pl


@dataclass
class LineProblem:
    """Line landmarks of a BA window.

    lines: line id -> (6,) Plücker (n, d) world initial guess. obs_kf, obs_line: (M,) ids of each
    observation's keyframe and line; obs_seg: (M,4) observed segment (u1, v1, u2, v2) ideal pixels.
    sigma: pixel std of an end-point distance; prior_sigma_rad: weak prior on (U, W), radians.
    obs_rho: (M,2) measured inverse depths of the end points (RGB-D / stereo; NaN: none) whitened by ``depth_weight``
    (fx b / sigma: a virtual disparity); "window" mode only.
    """

    lines: dict[int, np.ndarray]
    obs_kf: np.ndarray
    obs_line: np.ndarray
    obs_seg: np.ndarray
    sigma: float = 1.0
    prior_sigma_rad: float = 1.0  # regularises only: a pixel of end-point distance weighs ~1e4 times more
    chi2: float = 5.991  # 95 % of chi2(2), two end-point distances
    mode: Literal["window", "landmark"] = "window"  # one structureless factor, or line variables (see line_terms)
    obs_rho: np.ndarray | None = None
    depth_weight: float = 0.0

    @property
    def has_depth(self) -> bool:
        return self.obs_rho is not None and self.depth_weight > 0

    def inliers(self, chi2: np.ndarray) -> np.ndarray:
        """(M,) chi2 of each observation (``line_chi2``) -> inlier mask: ``chi2`` for the two end-point
        distances, raised to chi2(3) / chi2(4) at 95 % where one / both end points have a depth."""
        if not self.has_depth:
            return chi2 <= self.chi2
        n = np.isfinite(np.asarray(self.obs_rho, dtype=np.float64).reshape(-1, 2)).sum(axis=1)
        return chi2 <= np.array([self.chi2, 7.815, 9.488])[n]


def line_terms(lp: LineProblem, kf_in_graph: set[int], K_L: np.ndarray, huber_k: float,
               T_body_cam: np.ndarray | None = None, held_kf: set[int] = frozenset()) -> tuple[list[gtsam.NonlinearFactor], gtsam.Values, LineWindow | list[int]]:
    """Factors, initial values and a handle for ``line_estimates``: lines with >= 2 observations in
    keyframes of the graph. ``mode`` "window": one structureless factor (``line_window``), no values;
    "landmark": a ``line_factor`` + weak priors per line, lines as LU/LW values. T_body_cam: the graph's
    pose variables are body poses (visual-inertial BA; "window" mode only). held_kf: keyframes the graph holds
    fixed (tight priors): the window factor leaves their columns out (a local BA window holds about two thirds of
    the keyframes that see its lines) and reads their poses as constants."""
    if T_body_cam is not None and lp.mode != "window":
        raise ValueError("line landmarks on body poses (visual-inertial BA) need LineProblem.mode 'window'")
    if lp.has_depth and lp.mode != "window":
        raise ValueError("line end-point depths (LineProblem.obs_rho) need LineProblem.mode 'window'")
    facs: list[gtsam.NonlinearFactor] = []
    values = gtsam.Values()
    kf = np.asarray(lp.obs_kf, dtype=np.int64)
    ln = np.asarray(lp.obs_line, dtype=np.int64)
    seg = np.asarray(lp.obs_seg, dtype=np.float64).reshape(-1, 4)
    good = {j for j, L in lp.lines.items() if np.isfinite(L).all()}
    ok = np.isin(kf, np.fromiter(kf_in_graph, np.int64, len(kf_in_graph))) & np.isin(ln, np.fromiter(good, np.int64, len(good)))
    ids, counts = np.unique(ln[ok], return_counts=True)
    ids = ids[counts >= 2]
    ok &= np.isin(ln, ids)
    if lp.mode == "window":
        pose_keys = sorted(set(kf[ok].tolist()))
        pos = {k: i for i, k in enumerate(pose_keys)}
        idx = {j: i for i, j in enumerate(ids.tolist())}
        win = LineWindow(np.array([lp.lines[j] for j in ids.tolist()]).reshape(-1, 6),
                         np.array([idx[j] for j in ln[ok].tolist()], dtype=np.int64),
                         np.array([pos[k] for k in kf[ok].tolist()], dtype=np.int64), seg[ok],
                         [X(k) for k in pose_keys], K_L, lp.sigma, huber_k, T_body_cam,
                         np.asarray(lp.obs_rho, dtype=np.float64).reshape(-1, 2)[ok] if lp.has_depth else None,
                         lp.depth_weight, {X(k) for k in held_kf})
        win.line_ids = ids.tolist()  # window row -> line id
        f = win.factor()
        return ([f] if f is not None else []), values, win
    order = np.flatnonzero(ok)
    order = order[np.lexsort((kf[order], ln[order]))]
    for j in ids.tolist():
        rows = order[ln[order] == j]
        facs.append(lf.line_factor(j, kf[rows].tolist(), seg[rows], K_L, lp.sigma, huber_k))
        if len(rows) < 3:  # two views fix a line exactly, with no margin: regularise (a prior biases, so only here)
            facs.extend(lf.line_priors(j, lp.lines[j], lp.prior_sigma_rad))
        lf.insert_line(values, j, lp.lines[j])
    return facs, values, ids.tolist()


def factors_within(facs: list[gtsam.NonlinearFactor], values: gtsam.Values) -> list[gtsam.NonlinearFactor]:
    """The factors whose keys are all in ``values`` (a keyframe that lost every point factor in BA's second
    round is dropped from it; its line factors must go too)."""
    return [f for f in facs if all(values.exists(k) for k in f.keys())]


def line_estimates(est: gtsam.Values, handle: LineWindow | list[int]) -> dict[int, np.ndarray]:
    """{line id: (6,) Plücker, |d| = 1} for the lines in the graph, at the estimate ``est``."""
    if isinstance(handle, LineWindow):
        Twc = handle.camera_poses(est)
        if len(Twc):
            handle.U, handle.w, _ = handle.lines_at(Twc)
        return dict(zip(handle.line_ids, handle.lines()))
    return {j: lf.line_from_values(est, j) for j in handle}


def line_chi2(lp: LineProblem, poses: dict[int, np.ndarray], lines: dict[int, np.ndarray], K_L: np.ndarray) -> np.ndarray:
    """(M,) whitened squared end-point distances of every observation, with its end points' inverse-depth
    rows where measured (inf where its keyframe or line is unknown or the line projects degenerately).
    Vectorised over observations."""
    kf = np.asarray(lp.obs_kf, dtype=np.int64)
    ln = np.asarray(lp.obs_line, dtype=np.int64)
    out = np.full(len(kf), np.inf)
    ok = np.array([k in poses and j in lines for k, j in zip(kf.tolist(), ln.tolist())], dtype=bool)
    if not ok.any():
        return out
    Tcw = np.linalg.inv(np.array([poses[k] for k in kf[ok].tolist()]))
    L = np.array([lines[j] for j in ln[ok].tolist()])
    Lc = np.einsum("mij,mj->mi", _line_maps(Tcw), L)
    l = Lc[:, :3] @ K_L.T
    with np.errstate(invalid="ignore", divide="ignore"):
        seg = np.asarray(lp.obs_seg, dtype=np.float64).reshape(-1, 4)[ok]
        d = pl.segment_distances(seg, l)
        out[ok] = np.sum(d * d, axis=1) / lp.sigma**2
        if lp.has_depth:
            rho_obs = np.asarray(lp.obs_rho, dtype=np.float64).reshape(-1, 2)[ok]
            ed = lp.depth_weight * (rho_obs - pl.inverse_depth(Lc[:, :3], Lc[:, 3:], pl.end_rays(seg, K_L))[0])
            out[ok] += np.sum(np.where(np.isnan(rho_obs), 0.0, ed * ed), axis=1)
    out[~np.isfinite(out)] = np.inf
    return out


def _line_maps(T: np.ndarray) -> np.ndarray:
    """(M,4,4) transforms -> (M,6,6) Plücker maps (``plucker.line_transform_matrix``, stacked)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    tx = np.zeros((len(T), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    H = np.zeros((len(T), 6, 6))
    H[:, :3, :3], H[:, :3, 3:], H[:, 3:, 3:] = R, tx @ R, R
    return H


def camera_K_L(camera) -> np.ndarray:
    """(3,3) line projection matrix of a ``StereoCamera`` / ``PinholeCamera``."""
    return pl.line_projection_matrix(camera.fx, camera.fy, camera.cx, camera.cy)

