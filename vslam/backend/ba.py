"""Local bundle adjustment (GTSAM) and pose-only refinement (numpy) of a stereo-like pinhole camera.

Measurements are *ideal* (undistorted) pixels of the left camera with the
pinhole K of cam0. A stereo-like measurement adds ``ur``, the x coordinate the
point would have in a virtual right camera shifted by ``baseline`` along +x
(stereo: the matched right keypoint, rectified; RGB-D: ``u - fx * baseline /
depth`` with a virtual baseline), NaN for a monocular measurement.
Model (identical to ``gtsam.StereoCamera(Pose3(T_world_cam), Cal3_S2Stereo(fx, fy, 0, cx, cy, b))``):
``p = T_cam_world p_w;  u = fx X/Z + cx;  v = fy Y/Z + cy;  ur = u - fx b / Z``.

Local BA (``local_bundle_adjustment``), after ORB-SLAM2 ``Optimizer::LocalBundleAdjustment``:

1. *Screen*: an observation with a NaN, or whose point is behind its camera (z <= 1e-6 m) at the initial
   guess, gets no factor and is reported as an outlier. Points / keyframes left without factors are
   returned unchanged. A point whose only valid observation is stereo-like (three residuals on its three
   unknowns) carries no information about any pose: it gets no factor either and is set, after the poses,
   to its measurement back-projected from its keyframe (zero residual, the exact minimum), unless that
   keyframe is weakly tied to the window (``BackendConfig.closed_form_min_tied``). On RGB-D these are
   many of the window's points (new points of the newest keyframe), so BA gets much cheaper, the poses the
   same up to LM damping (docs/backend.md, "Local BA timings").
2. *Build*: keys ``X(kf_id)`` (Pose3 = T_world_cam) and ``L(point_id)``; one ``GenericStereoFactor3D``
   (finite ur and baseline > 0) or ``GenericProjectionFactorCal3_S2`` per observation, isotropic
   ``pixel_sigma`` (or ``BAProblem.obs_sigma``) inside a Huber model. Fixed keyframes are held by a
   PriorFactorPose3 of sigma 1e-6 (NonlinearEqualityPose3 gives the same result but is slower, see
   ``factors.py``). If no observed keyframe is fixed, the one with the lowest id is held instead (gauge:
   6 DOF; for mono-only windows the scale then stays free, only held near the initial guess by LM damping --
   pass at least two fixed keyframes for mono).
   With ``BAProblem.lines`` (line features) the window's line observations join both LM rounds as one
   structureless factor (``line_ba`` / ``line_window``); ``BAResult.lines`` / ``line_inliers`` come back.
3. *Optimise*: Levenberg-Marquardt, ``max_iterations`` (lambda settings in ``factors.lm_params``). With
   ``BackendConfig.solver = "numpy"`` steps 2-5 run on the same cost in ``vslam.backend.schur`` instead of a
   GTSAM graph (same estimate to the LM tolerance, in less time: docs/backend.md).
4. *Classify*: chi2 test on each observation's unrobust whitened squared error (chi2_mono / chi2_stereo).
5. *Refine*: the outlier factors are dropped and LM runs ``refine_iterations`` more (ORB-SLAM2: 10) from
   the first-round estimate; variables left with no factor keep their first-round value. The Huber kernel
   stays on (ORB-SLAM2 drops it): the few undetected outliers then stay harmless, and on exact synthetic
   data the second round still lands on the exact solution. Then every screened observation is
   classified again at the final estimate -> ``BAResult.inliers``.

``BAResult.poses`` holds every keyframe *not* in ``problem.fixed`` (including a gauge-anchored one, which is
returned unchanged); fixed keyframes are left out -- the caller's copies are the truth, bit for bit.
``points`` holds every point (unobserved / fully screened ones unchanged). ``initial_error`` /
``final_error``: robust (Huber) graph error of *all* screened observations at the initial guess and at
the final estimate (the same graph, so they compare). ``iterations``: LM iterations of both rounds.
``ms``: build, optimize (both LM rounds), classify (both), total. The closed-form points are in neither error.

Timings: ``python -m tests.backend.bench_ba``, results in docs/backend.md ("Local BA timings"). A GTSAM LM
iteration is dominated by elimination, GTSAM's per-clique overhead over many tiny point cliques, and the
Python-side build pays per factor.

Why a window and not iSAM2: on a growing stereo map, iSAM2 over the whole history was slightly more accurate
than windowed LM at several times the time per keyframe, and its time grows with the map
(``python -m tests.backend.bench_solvers --kf 30``; numbers in docs/backend.md). So local mapping uses the
window; loop closing adds the global optimisation (``vslam.loop``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np

from vslam.backend import factors as fx
from vslam.backend.line_ba import LineProblem, camera_K_L, factors_within, line_chi2, line_estimates, line_terms
from vslam.backend.pose_only import refine_pose
from vslam.backend.projection import backproject_cam
from vslam.backend.schur import robust_cost, schur_lm
from vslam.backend.window import DenseWindow, dense_window
from vslam.geometry.se3 import inv_T


#: ``BackendConfig.solver = "numpy"`` solves windows of at most this many observed keyframes; larger problems
#: (global BA after a loop) go to GTSAM: the dense Schur blocks grow with keyframes x points.
NUMPY_MAX_POSES = 24


@dataclass(frozen=True)
class BackendConfig:
    pixel_sigma: float = 1.0  # std of a keypoint measurement, pixels
    huber_k: float = 1.345  # Huber threshold in sigmas (robust loss on every visual factor)
    chi2_mono: float = 5.991  # 95 % of chi2(2): an observation above this after BA is an outlier
    chi2_stereo: float = 7.815  # 95 % of chi2(3)
    # LM iterations of local BA. Each keyframe's BA starts from tracked poses, so few are needed: fewer
    # iterations (4 + 2) kept the ATE of the bench rows and cut BA time per keyframe (docs/backend.md, "BA
    # settings").
    max_iterations: int = 4
    rgbd_virtual_baseline: float = 0.08  # metres; RGB-D depth as a virtual stereo pair (ORB-SLAM2 uses bf/fx ~ 0.08)
    # RGB-D: std (px) of the virtual disparity fx*b/z, independent of the keypoint's own pixel noise.
    # ORB-SLAM2 gives uR the keypoint's sigma (1 px) as if it were a second keypoint: with b = 0.08 that is a
    # depth std of ~5 % at 2 m, far above a depth sensor (Kinect: sigma_z ~ 1.4e-3 z^2, i.e. a constant
    # ~0.06 px of this disparity), and local BA then trades depth for the rotation/translation ambiguity:
    # on the synthetic loop room every keyframe BA *added* rotation error (docs/backend.md, "BA settings").
    # 0 = the ORB-SLAM2 model. Swept in ``vslam bench`` rows.
    rgbd_disparity_sigma: float = 0.1
    # Rectified stereo with sub-pixel refinement (``vslam.features.stereo``): the disparity is measured against
    # the left keypoint, so the RGB-D model applies in principle. 0 (uR as an independent keypoint, as for the
    # unrectified EuRoC rig) measured better (docs/backend.md, "BA settings"; its error grows with the pyramid
    # level, which one sigma does not model).
    stereo_disparity_sigma: float = 0.0
    # RGB-D: an observation that fails the stereo chi2 test but passes the mono one on its pixel alone keeps
    # its match as a mono observation (its depth is dropped) instead of losing it. Slightly more accurate on
    # TUM teddy but much slower (more keyframes); the synthetic rows (exact depth) do not change. Off
    # (docs/backend.md, "BA settings").
    rgbd_depth_outliers_as_mono: bool = False
    refine_iterations: int = 2  # LM iterations of local BA's second round, outliers removed (ORB-SLAM2: 10)
    # Single-view stereo points are solved in closed form (module docstring, step 1) only in keyframes with at
    # least this many observations of points another keyframe of the window sees. A keyframe tied to the window
    # by fewer is barely determined by it (seen on the synthetic tight loop: docs/backend.md, "BA settings");
    # there its single-view points' factors stay in the graph, where LM's damping of the points holds the pose
    # near its tracked value, as before this shortcut.
    closed_form_min_tied: int = 50
    # Local BA's solver: "numpy" (``vslam.backend.schur``: points eliminated by a dense Schur complement over the
    # window's free poses) or "gtsam" (the factor graph of ``factors``); the same cost and LM settings, the same
    # estimates to the LM tolerance per window. Windows with line landmarks or more than NUMPY_MAX_POSES keyframes
    # (global BA), and visual-inertial windows, go to GTSAM either way. numpy by default: about half of GTSAM's
    # CPU per window (GTSAM pays per factor built from Python and per point clique eliminated), with about the
    # same ATE on the bench's rows (docs/backend.md).
    solver: Literal["gtsam", "numpy"] = "numpy"
    pose_rounds: int = 4  # pose-only: optimise / classify rounds (ORB-SLAM2: 4)
    pose_iterations: int = 10  # pose-only: LM iterations per round (ORB-SLAM2: 10)


class _CompactPoints:
    """Pickles a ``points`` dict {id: (3,) array} as two arrays: the BA worker ships every window's points both
    ways, and a dict of thousands of small arrays was slow to pickle and unpickle on the tracking thread, two
    arrays are not (docs/speed.md). Same values after the round trip."""

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        pts = state["points"]
        state["points"] = (np.fromiter(pts.keys(), np.int64, len(pts)),
                           np.array(list(pts.values()), dtype=np.float64).reshape(-1, 3))
        return state

    def __setstate__(self, state: dict) -> None:
        ids, xyz = state["points"]
        self.__dict__.update(state)
        self.points = dict(zip(ids.tolist(), xyz))


@dataclass(frozen=True)
class StereoCamera:
    """Pinhole of the (rectified) left camera; baseline in metres for stereo-like measurements (0 = mono only).

    disparity_sigma (px): 0 -> uR is an independent measurement with the keypoint's pixel sigma (a matched
    right keypoint: stereo); > 0 -> uR = uL - d with the disparity d of this std independent of uL (a depth
    sensor: RGB-D). The whitened stereo residual is then (e_uL / s, e_v / s, (e_uL - e_uR) / disparity_sigma).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float = 0.0
    disparity_sigma: float = 0.0


@dataclass
class BAProblem(_CompactPoints):
    """A local BA window.

    poses: keyframe id -> (4,4) T_world_cam initial guess.
    fixed: keyframe ids whose pose is held constant (they anchor the gauge).
    points: point id -> (3,) world position initial guess.
    obs_kf, obs_pt: (M,) int ids of each observation's keyframe and point (ids >= 0).
    obs_uv: (M,2) ideal pixels; obs_ur: (M,) virtual right x, NaN for mono.
    obs_sigma: optional (M,) pixel std per observation (e.g. 1.2**octave); None -> cfg.pixel_sigma.
    """

    poses: dict[int, np.ndarray]
    fixed: set[int]
    points: dict[int, np.ndarray]
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    obs_uv: np.ndarray
    obs_ur: np.ndarray
    obs_sigma: np.ndarray | None = None
    lines: LineProblem | None = None  # line landmarks (``vslam.backend.line_ba``), None: points only
    # relative poses between keyframes of ``poses`` (``vslam.mapping.map.PoseLink``: a, b, T_a_b, cov), each a
    # robust BetweenFactorPose3 in both LM rounds; a keyframe they name is optimised even with no observation
    links: list | None = None

    def usable_links(self) -> list:
        """The ``links`` between two different keyframes of ``poses`` (others cannot enter this window's graph)."""
        return [ln for ln in self.links or () if ln.a != ln.b and ln.a in self.poses and ln.b in self.poses]


@dataclass
class BAResult(_CompactPoints):
    poses: dict[int, np.ndarray]  # optimized poses of the non-fixed keyframes (fixed ones left out)
    points: dict[int, np.ndarray]  # every point of the problem (unobserved ones unchanged)
    inliers: np.ndarray  # (M,) bool, chi2 test after optimisation
    iterations: int = 0
    initial_error: float = float("nan")
    final_error: float = float("nan")
    ms: dict[str, float] = field(default_factory=dict)
    lines: dict[int, np.ndarray] = field(default_factory=dict)  # optimised Plücker lines (|d| = 1) of the graph
    line_inliers: np.ndarray | None = None  # (M_lines,) bool, chi2 test at the estimate; None without lines
    # (M,) bool: RGB-D outliers whose pixel alone passes the mono test (the match holds, the depth does not);
    # None unless BackendConfig.rgbd_depth_outliers_as_mono
    depth_only: np.ndarray | None = None


def local_bundle_adjustment(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig = BackendConfig(),
                            cache: fx.FactorCache | None = None) -> BAResult:
    """Optimise the window's non-fixed poses and all observed points; the steps are in the module docstring.

    ``cache``: the caller's ``factors.FactorCache``, whose factors of the previous window are reused where this
    window has the same observations (the result is the same with or without it; the numpy solver ignores it)."""
    t0 = time.perf_counter()
    win = dense_window(problem, camera, cfg)
    valid = np.isfinite(win.chi2(win.Twc0, win.P0, camera))  # screen: NaN anywhere or behind the camera
    links = problem.usable_links()
    Twc0 = win.Twc0.copy()  # one copy whose rows the result holds: the window's arrays stay the initial guess
    result = BAResult(
        poses={k: Twc0[i] for i, k in enumerate(win.kf_ids.tolist()) if k not in problem.fixed},
        points=dict(zip(win.pt_ids.tolist(), win.P0.copy())),
        inliers=np.zeros(win.kf.shape[0], dtype=bool),
    )
    if not valid.any() and not links:
        result.ms = {"build": 0.0, "optimize": 0.0, "classify": 0.0, "total": 1e3 * (time.perf_counter() - t0)}
        return result

    closed = _single_view(win, valid, cfg.closed_form_min_tied)
    idx = np.flatnonzero(valid & ~closed)
    if idx.size == 0 and not links:  # only single-view points: nothing constrains a pose
        P = _backprojected(win, closed, win.Twc0, win.P0, camera)
        for i in win.ip[closed].tolist():
            result.points[int(win.pt_ids[i])] = P[i]
        result.inliers = valid & (win.chi2(win.Twc0, P, camera) <= win.thr)
        result.ms = {"build": 0.0, "optimize": 0.0, "classify": 0.0, "total": 1e3 * (time.perf_counter() - t0)}
        return result
    used_k, used_p = np.unique(win.ik[idx]), np.unique(win.ip[idx])  # sorted, like GTSAM's key order
    linked = {k for ln in links for k in (ln.a, ln.b)}
    used_k = np.union1d(used_k, np.searchsorted(win.kf_ids, sorted(linked))).astype(np.int64)
    if cfg.solver == "numpy" and problem.lines is None and not links and len(used_k) <= NUMPY_MAX_POSES:
        return _local_ba_numpy(problem, camera, cfg, win, valid, closed, idx, used_k, result, t0)
    rows = (win.kf[idx], win.pt[idx], win.meas[idx], win.stereo[idx], win.sigma[idx])
    if cache is not None:
        builder, facs = cache.builder(camera, cfg.huber_k), cache.factors(camera, cfg.huber_k, *rows)
    else:
        builder = fx.FactorBuilder(camera, cfg.huber_k)
        facs = builder.factors(*rows)
    anchors = _anchors(problem.fixed, win.kf_ids[used_k].tolist())
    holds = [builder.hold(fx.X(k), problem.poses[k]) for k in anchors]
    holds += [builder.between(ln.a, ln.b, ln.T_a_b, ln.cov) for ln in links]
    values = _initial_values(win.Twc0[used_k], win.P0[used_p], win.kf_ids[used_k], win.pt_ids[used_p])
    line_facs, line_ids = [], []
    if problem.lines is not None:  # line factors join both LM rounds (their Huber kernel is per observation)
        line_facs, line_values, line_ids = line_terms(problem.lines, set(win.kf_ids[used_k].tolist()),
                                                      camera_K_L(camera), cfg.huber_k, held_kf=set(anchors))
        values.insert(line_values)
    graph = _graph(facs + holds + line_facs)
    t1 = time.perf_counter()

    est, iters, initial_error = _levenberg_marquardt(graph, values, cfg.max_iterations, schur=True)
    t2 = time.perf_counter()

    keep = win.chi2(*_estimate_arrays(est, win, used_k, used_p), camera)[idx] <= win.thr[idx]
    t3 = time.perf_counter()

    if cfg.refine_iterations > 0 and keep.any():  # ORB-SLAM2: drop the outlier factors, optimise again
        start = _without(est, _orphans(win, idx[keep], used_k, used_p, set(anchors) | linked))
        graph2 = _graph(list(itertools.compress(facs, keep.tolist())) + holds + factors_within(line_facs, start))
        est2, more, _ = _levenberg_marquardt(graph2, start, cfg.refine_iterations, schur=True)
        est = gtsam.Values(est)
        est.update(est2)  # a variable that lost all its factors keeps its first-round value
        iters += more
    t4 = time.perf_counter()

    Twc, P = _estimate_arrays(est, win, used_k, used_p)
    P = _backprojected(win, closed, Twc, P, camera)
    result.inliers = valid & (win.chi2(Twc, P, camera) <= win.thr)
    if cfg.rgbd_depth_outliers_as_mono and camera.disparity_sigma > 0:
        result.depth_only = valid & win.stereo & ~result.inliers & (win.uv_chi2(Twc, P, camera) <= cfg.chi2_mono)
    for i in used_k.tolist():
        k = int(win.kf_ids[i])
        if k in result.poses and k not in anchors:  # a gauge anchor comes back unchanged
            result.poses[k] = Twc[i]
    # every point: those not in the graph nor solved in closed form have their initial value in P
    result.points = dict(zip(win.pt_ids.tolist(), P))
    result.iterations = iters
    result.initial_error = initial_error  # LM evaluated it first thing (same graph and values)
    result.final_error = float(graph.error(est))
    if problem.lines is not None:
        result.lines = line_estimates(est, line_ids)
        poses = {int(k): Twc[i] for i, k in enumerate(win.kf_ids.tolist())}
        result.line_inliers = problem.lines.inliers(line_chi2(problem.lines, poses, result.lines, camera_K_L(camera)))
    t5 = time.perf_counter()
    result.ms = {
        "build": 1e3 * (t1 - t0),
        "optimize": 1e3 * ((t2 - t1) + (t4 - t3)),
        "classify": 1e3 * ((t3 - t2) + (t5 - t4)),
        "total": 1e3 * (t5 - t0),
    }
    return result


def _local_ba_numpy(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig, win: DenseWindow, valid: np.ndarray,
                    closed: np.ndarray, idx: np.ndarray, used_k: np.ndarray, result: BAResult, t0: float) -> BAResult:
    """Steps 2-5 of ``local_bundle_adjustment`` with ``schur.schur_lm`` in place of the GTSAM graph."""
    anchors = _anchors(problem.fixed, win.kf_ids[used_k].tolist())
    free = np.zeros(win.kf_ids.size, bool)
    free[used_k] = True
    free &= ~np.isin(win.kf_ids, anchors)
    Tcw = inv_T(win.Twc0)
    ik, ip, meas, st, sig = win.ik[idx], win.ip[idx], win.meas[idx], win.stereo[idx], win.sigma[idx]
    t1 = time.perf_counter()
    Tcw, P, iters, initial_error = schur_lm(Tcw, win.P0, ik, ip, meas, st, sig, free, camera, cfg.huber_k,
                                            cfg.max_iterations)
    t2 = time.perf_counter()
    keep = win.chi2(inv_T(Tcw), P, camera)[idx] <= win.thr[idx]
    t3 = time.perf_counter()
    if cfg.refine_iterations > 0 and keep.any():
        Tcw, P, more, _ = schur_lm(Tcw, P, ik[keep], ip[keep], meas[keep], st[keep], sig[keep], free, camera,
                                   cfg.huber_k, cfg.refine_iterations)
        iters += more
    t4 = time.perf_counter()
    Twc = inv_T(Tcw)
    P = _backprojected(win, closed, Twc, P, camera)
    result.inliers = valid & (win.chi2(Twc, P, camera) <= win.thr)
    if cfg.rgbd_depth_outliers_as_mono and camera.disparity_sigma > 0:
        result.depth_only = valid & win.stereo & ~result.inliers & (win.uv_chi2(Twc, P, camera) <= cfg.chi2_mono)
    for i in np.flatnonzero(free).tolist():
        result.poses[int(win.kf_ids[i])] = Twc[i]
    moved = np.union1d(ip, win.ip[closed])
    result.points.update(zip(win.pt_ids[moved].tolist(), P[moved]))
    result.iterations = iters
    result.initial_error = initial_error
    result.final_error = robust_cost(Tcw, P, ik, ip, meas, st, sig, camera, cfg.huber_k)
    t5 = time.perf_counter()
    result.ms = {"build": 1e3 * (t1 - t0), "optimize": 1e3 * ((t2 - t1) + (t4 - t3)),
                 "classify": 1e3 * ((t3 - t2) + (t5 - t4)), "total": 1e3 * (t5 - t0)}
    return result


def optimize_pose(
    T_world_cam: np.ndarray,
    pts_world: np.ndarray,
    uv: np.ndarray,
    ur: np.ndarray,
    camera: StereoCamera,
    cfg: BackendConfig = BackendConfig(),
    sigma: np.ndarray | float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pose-only refinement with fixed points: -> (T_world_cam (4,4), inliers (N,) bool).

    T_world_cam: (4,4) initial guess; pts_world: (N,3) metres, held fixed; uv: (N,2) ideal pixels;
    ur: (N,) virtual right x or NaN (mono); sigma: optional pixel std, scalar or (N,) (None: cfg.pixel_sigma).
    ORB-SLAM2's 4 rounds of robust LM + chi2 classification (``vslam.backend.pose_only``). Rows with a
    NaN are outliers; with fewer than 3 usable rows the input pose is returned (inliers: chi2 at it).
    """
    return refine_pose(T_world_cam, pts_world, uv, ur, camera, cfg, sigma)


def _levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, iterations: int, schur: bool = False):
    """-> (estimate, LM iterations run, graph error at ``values``). ``schur``: eliminate every landmark before the
    poses, sequentially.

    That is the Schur complement of BA solvers: each point (or line) goes first, leaving only the small dense
    system of the window's poses. On TUM teddy's local BA windows it gives the same estimate as GTSAM's default
    COLAMD + multifrontal Cholesky in a little less time; multifrontal with this order is slower than the
    default (docs/backend.md, "Local BA timings")."""
    params = fx.lm_params(iterations)
    if schur:
        keys = np.asarray(values.keys(), dtype=np.uint64)
        is_pose = (keys >> np.uint64(56)) == ord("x")  # a Symbol's character is its key's top byte
        params.setOrdering(gtsam.Ordering(np.concatenate([keys[~is_pose], keys[is_pose]]).tolist()))  # poses last
        params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial_error = float(opt.error())  # computed by the constructor: no second pass over the graph
    est = opt.optimize()
    return est, int(opt.iterations()), initial_error


def _single_view(win: DenseWindow, valid: np.ndarray, min_tied: int) -> np.ndarray:
    """(M,) bool: the valid stereo observations (positive disparity) that are their point's only valid one,
    in keyframes with at least ``min_tied`` valid observations of points seen more than once.

    Three residuals on three unknowns: such a point carries no information about any pose (its Schur
    complement vanishes), it only costs a clique. It is solved in closed form after the poses instead.
    ``BackendConfig.closed_form_min_tied`` says why a weakly tied keyframe keeps them."""
    n_views = np.bincount(win.ip[valid], minlength=win.pt_ids.size)
    single = valid & win.stereo & (n_views[win.ip] == 1) & (win.meas[:, 0] - win.meas[:, 2] > 0)
    tied = np.bincount(win.ik[valid & (n_views[win.ip] > 1)], minlength=win.kf_ids.size)
    return single & (tied[win.ik] >= min_tied)


def _backprojected(win: DenseWindow, obs: np.ndarray, Twc: np.ndarray, P: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """P with the points of the observations ``obs`` (bool (M,)) set to their zero-residual position: the
    stereo measurement (uL, v, uR) back-projected from its keyframe's pose in Twc."""
    i = np.flatnonzero(obs)
    if i.size == 0:
        return P
    pc = backproject_cam(win.meas[i], camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
    T = Twc[win.ik[i]]
    P = P.copy()
    P[win.ip[i]] = np.einsum("mij,mj->mi", T[:, :3, :3], pc) + T[:, :3, 3]
    return P


def _orphans(win: DenseWindow, kept: np.ndarray, used_k, used_p, anchors: set[int]) -> list[int]:
    """Keys of variables with no factor left once only the observations ``kept`` (indices) remain (``anchors``:
    keyframes with other factors: holds, links)."""
    lost_p = np.setdiff1d(used_p, win.ip[kept])
    lost_k = [k for k in win.kf_ids[np.setdiff1d(used_k, win.ik[kept])].tolist() if k not in anchors]
    return [fx.X(k) for k in lost_k] + [fx.L(int(j)) for j in win.pt_ids[lost_p].tolist()]


def _without(values: gtsam.Values, keys: list[int]) -> gtsam.Values:
    """Copy of values minus keys (GTSAM's sequential solvers reject a variable that no factor touches)."""
    if not keys:
        return values
    out = gtsam.Values(values)
    for key in keys:
        out.erase(key)
    return out


def _estimate_arrays(est: gtsam.Values, win: DenseWindow, used_k, used_p) -> tuple[np.ndarray, np.ndarray]:
    """(K,4,4) T_world_cam and (P,3) points at the estimate; variables not in the graph keep their initial value."""
    Twc, P = win.Twc0.copy(), win.P0.copy()
    rows = gtsam.utilities.extractPose3(est)  # (k,12): R row-major then t, in key order = used_k order
    Twc[used_k, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    Twc[used_k, :3, 3] = rows[:, 9:]
    P[used_p] = gtsam.utilities.extractPoint3(est)  # key order = used_p order
    return Twc, P


def _anchors(fixed: set[int], observed_kf: list[int]) -> list[int]:
    """Keyframes to hold: the fixed ones that are observed, else the observed one with the lowest id (gauge)."""
    held = [k for k in observed_kf if k in fixed]
    return held if held else observed_kf[:1]


def _initial_values(Twc: np.ndarray, P: np.ndarray, kfs: np.ndarray, pts: np.ndarray) -> gtsam.Values:
    """Values with X(kfs[i]) = Pose3(Twc[i]) and L(pts[i]) = P[i]."""
    values = gtsam.Values()
    for key, T in zip(fx.symbol_keys("x", kfs), Twc):
        values.insert(key, fx.pose3(T))
    insert = values.insertPoint3  # the typed insert: no overload resolution per point
    for key, p in zip(fx.symbol_keys("l", pts), P):
        insert(key, p)
    return values


def _graph(factors: list) -> gtsam.NonlinearFactorGraph:
    graph = gtsam.NonlinearFactorGraph()
    add = graph.add
    for f in factors:
        add(f)
    return graph
