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
   returned unchanged.
2. *Build*: one ``GenericStereoFactor3D`` (finite ur and baseline > 0) or ``GenericProjectionFactorCal3_S2``
   per observation, isotropic ``pixel_sigma`` (or ``BAProblem.obs_sigma``) inside a Huber model.
   Fixed keyframes are held by ``NonlinearEqualityPose3``. If no observed keyframe is fixed, the one with
   the lowest id is held instead (gauge: 6 DOF; for mono-only windows the scale stays free and is only
   held near the initial guess by LM damping -- pass at least two fixed keyframes for mono).
3. *Optimise*: Levenberg-Marquardt, ``max_iterations``.
4. *Classify*: chi2 test on each observation's unrobust whitened squared error (chi2_mono / chi2_stereo).
5. *Refine*: the outlier factors are dropped and LM runs ``refine_iterations`` more (still Huber: a few
   undetected outliers remain harmless). ORB-SLAM2 drops the kernel here; with 1-2 % of residual outliers
   keeping it costs nothing in accuracy on our synthetic tests. Then all screened observations are
   classified again at the final estimate -> ``BAResult.inliers``.

``BAResult.poses`` holds every keyframe *not* in ``problem.fixed`` (including a gauge-anchored one, which is
returned unchanged); fixed keyframes are left out -- the caller's copies are the truth, bit for bit.
``initial_error`` / ``final_error`` are the robust (Huber) graph error of *all* screened observations at the
initial guess and at the final estimate (the same graph, so they compare). ``iterations`` = LM iterations of
both rounds. ``ms``: build, optimize (both LM rounds), classify (both), total.

Measured (``python -m tests.backend.bench_ba``; 2-core Xeon, single thread, median of 5):

=====================================================================  =========================
local BA, 10 kf x 300 obs (3000 obs, ~1500 pts, 2 fixed, 50 % stereo)  see BENCH table below
pose-only, 300 / 500 points, 20 % outliers, numpy (this module)        see BENCH table below
=====================================================================  =========================
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from vslam.backend import factors as fx
from vslam.backend.pose_only import refine_pose
from vslam.backend.projection import chi2_thresholds, measurement_matrix, whitened_sq_errors
from vslam.geometry.se3 import inv_T


@dataclass(frozen=True)
class BackendConfig:
    pixel_sigma: float = 1.0  # std of a keypoint measurement, pixels
    huber_k: float = 1.345  # Huber threshold in sigmas (robust loss on every visual factor)
    chi2_mono: float = 5.991  # 95 % of chi2(2): an observation above this after BA is an outlier
    chi2_stereo: float = 7.815  # 95 % of chi2(3)
    max_iterations: int = 10  # Levenberg-Marquardt iterations of local BA
    rgbd_virtual_baseline: float = 0.08  # metres; RGB-D depth as a virtual stereo pair (ORB-SLAM2 uses bf/fx ~ 0.08)
    refine_iterations: int = 5  # LM iterations of local BA's second round, outliers removed (ORB-SLAM2: 10)
    pose_rounds: int = 4  # pose-only: optimise / classify rounds (ORB-SLAM2: 4)
    pose_iterations: int = 10  # pose-only: LM iterations per round (ORB-SLAM2: 10)


@dataclass(frozen=True)
class StereoCamera:
    """Pinhole of the (rectified) left camera; baseline in metres for stereo-like measurements (0 = mono only)."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float = 0.0


@dataclass
class BAProblem:
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


@dataclass
class BAResult:
    poses: dict[int, np.ndarray]  # optimized poses of the non-fixed keyframes (fixed ones left out)
    points: dict[int, np.ndarray]  # every point of the problem (unobserved ones unchanged)
    inliers: np.ndarray  # (M,) bool, chi2 test after optimisation
    iterations: int = 0
    initial_error: float = float("nan")
    final_error: float = float("nan")
    ms: dict[str, float] = field(default_factory=dict)


@dataclass
class _Obs:
    """Observations as dense arrays: ids, dense indices into the sorted id lists, measurements."""

    kf: np.ndarray  # (M,) keyframe ids
    pt: np.ndarray  # (M,) point ids
    ik: np.ndarray  # (M,) index into kf_ids
    ip: np.ndarray  # (M,) index into pt_ids
    meas: np.ndarray  # (M,3) uL, v, uR (0 for mono)
    stereo: np.ndarray  # (M,) bool
    sigma: np.ndarray  # (M,) px
    thr: np.ndarray  # (M,) chi2 threshold


def local_bundle_adjustment(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig = BackendConfig()) -> BAResult:
    """Optimise the window's non-fixed poses and all observed points; see the module docstring for the steps."""
    t0 = time.perf_counter()
    kf_ids = np.array(sorted(problem.poses), dtype=np.int64)
    pt_ids = np.array(sorted(problem.points), dtype=np.int64)
    obs = _dense_observations(problem, camera, cfg, kf_ids, pt_ids)
    Twc0 = np.stack([np.asarray(problem.poses[k], np.float64) for k in kf_ids.tolist()]) if kf_ids.size else np.zeros((0, 4, 4))
    P0 = np.array([problem.points[j] for j in pt_ids.tolist()], dtype=np.float64).reshape(-1, 3)
    valid = np.isfinite(_chi2(obs, Twc0, P0, camera))  # screen: NaN anywhere or behind the camera -> no factor
    result = BAResult(
        poses={k: np.array(problem.poses[k], dtype=np.float64) for k in kf_ids.tolist() if k not in problem.fixed},
        points={j: np.array(problem.points[j], dtype=np.float64).reshape(3) for j in pt_ids.tolist()},
        inliers=np.zeros(obs.kf.shape[0], dtype=bool),
    )
    if not valid.any():
        result.ms = {"build": 0.0, "optimize": 0.0, "classify": 0.0, "total": 1e3 * (time.perf_counter() - t0)}
        return result

    idx = np.flatnonzero(valid)
    used_k, used_p = np.unique(obs.ik[idx]), np.unique(obs.ip[idx])  # sorted = GTSAM key order
    builder = fx.FactorBuilder(camera, cfg.huber_k)
    facs = builder.factors(obs.kf[idx], obs.pt[idx], obs.meas[idx], obs.stereo[idx], obs.sigma[idx])
    anchors = _anchors(problem, kf_ids[used_k].tolist())
    values = _initial_values(Twc0[used_k], P0[used_p], kf_ids[used_k], pt_ids[used_p])
    graph = _graph(facs, anchors, Twc0, kf_ids, builder)
    t1 = time.perf_counter()

    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, fx.lm_params(cfg.max_iterations))
    est = opt.optimize()
    iters = opt.iterations()
    t2 = time.perf_counter()

    Twc, P = _estimate_arrays(est, Twc0, P0, used_k, used_p)
    keep = _chi2(obs, Twc, P, camera)[idx] <= obs.thr[idx]
    t3 = time.perf_counter()

    if cfg.refine_iterations > 0 and keep.any():  # ORB-SLAM2: drop the outliers, optimise again
        graph2 = graph if keep.all() else _graph([f for f, k in zip(facs, keep.tolist()) if k], anchors, Twc0, kf_ids, builder)
        opt2 = gtsam.LevenbergMarquardtOptimizer(graph2, est, fx.lm_params(cfg.refine_iterations))
        est = opt2.optimize()
        iters += opt2.iterations()
    t4 = time.perf_counter()

    Twc, P = _estimate_arrays(est, Twc0, P0, used_k, used_p)
    result.inliers = valid & (_chi2(obs, Twc, P, camera) <= obs.thr)
    held = set(anchors)
    for i in used_k.tolist():
        k = int(kf_ids[i])
        if k in result.poses and k not in held:
            result.poses[k] = Twc[i]
    for i in used_p.tolist():
        result.points[int(pt_ids[i])] = P[i]
    result.iterations = int(iters)
    result.initial_error = float(graph.error(values))
    result.final_error = float(graph.error(est))
    t5 = time.perf_counter()
    result.ms = {
        "build": 1e3 * (t1 - t0),
        "optimize": 1e3 * ((t2 - t1) + (t4 - t3)),
        "classify": 1e3 * ((t3 - t2) + (t5 - t4)),
        "total": 1e3 * (t5 - t0),
    }
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


def _dense_observations(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig, kf_ids, pt_ids) -> _Obs:
    kf = np.asarray(problem.obs_kf, dtype=np.int64).reshape(-1)
    pt = np.asarray(problem.obs_pt, dtype=np.int64).reshape(-1)
    m = kf.shape[0]
    ik = np.searchsorted(kf_ids, kf)
    ip = np.searchsorted(pt_ids, pt)
    bad_k = (ik >= kf_ids.size) | (kf_ids[np.minimum(ik, max(kf_ids.size - 1, 0))] != kf) if m else np.zeros(0, bool)
    bad_p = (ip >= pt_ids.size) | (pt_ids[np.minimum(ip, max(pt_ids.size - 1, 0))] != pt) if m else np.zeros(0, bool)
    if m and (bad_k.any() or bad_p.any()):
        raise ValueError(
            f"BAProblem observations name unknown keyframes {sorted(set(kf[bad_k].tolist()))} "
            f"or points {sorted(set(pt[bad_p].tolist()))}"
        )
    meas, stereo = measurement_matrix(np.asarray(problem.obs_uv).reshape(m, 2), np.asarray(problem.obs_ur).reshape(m))
    if camera.baseline <= 0:
        stereo[:] = False
    sigma = np.full(m, cfg.pixel_sigma) if problem.obs_sigma is None else np.asarray(problem.obs_sigma, np.float64).reshape(m)
    thr = chi2_thresholds(stereo, cfg.chi2_mono, cfg.chi2_stereo)
    return _Obs(kf, pt, ik, ip, meas, stereo, np.where(sigma > 0, sigma, np.nan), thr)


def _chi2(obs: _Obs, Twc: np.ndarray, P: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """(M,) unrobust whitened squared errors at poses Twc (K,4,4) T_world_cam and points P (P,3); inf = NaN/behind."""
    if obs.kf.shape[0] == 0:
        return np.zeros(0)
    Tcw = inv_T(Twc)
    R, t = Tcw[obs.ik, :3, :3], Tcw[obs.ik, :3, 3]
    pc = np.einsum("mij,mj->mi", R, P[obs.ip]) + t
    chi2, _ = whitened_sq_errors(pc, obs.meas, obs.stereo, obs.sigma, camera)
    return chi2


def _estimate_arrays(est: gtsam.Values, Twc0, P0, used_k, used_p) -> tuple[np.ndarray, np.ndarray]:
    """(K,4,4) T_world_cam and (P,3) points at the estimate; variables not in the graph keep their initial value."""
    Twc, P = Twc0.copy(), P0.copy()
    rows = gtsam.utilities.extractPose3(est)  # (k,12): R row-major, t; in key order = used_k order
    Twc[used_k, :3, :3] = rows[:, :9].reshape(-1, 3, 3)
    Twc[used_k, :3, 3] = rows[:, 9:]
    P[used_p] = gtsam.utilities.extractPoint3(est)
    return Twc, P


def _anchors(problem: BAProblem, observed_kf: list[int]) -> list[int]:
    """Keyframes to hold: the fixed ones that are observed, else the observed one with the lowest id (gauge)."""
    held = [k for k in observed_kf if k in problem.fixed]
    return held if held else observed_kf[:1]


def _initial_values(Twc: np.ndarray, P: np.ndarray, kfs: np.ndarray, pts: np.ndarray) -> gtsam.Values:
    """Values with X(kfs[i]) = Twc[i] (Pose3) and L(pts[i]) = P[i] (Point3)."""
    values = gtsam.Values()
    for k, T in zip(kfs.tolist(), Twc):
        values.insert(fx.X(k), fx.pose3(T))
    for j, p in zip(pts.tolist(), P):
        values.insert(fx.L(j), p)
    return values


def _graph(facs, anchors: list[int], Twc0: np.ndarray, kf_ids: np.ndarray, builder) -> gtsam.NonlinearFactorGraph:
    """Visual factors plus one constraint per held keyframe (at its initial pose)."""
    graph = gtsam.NonlinearFactorGraph()
    for f in facs:
        graph.add(f)
    for k in anchors:
        graph.add(builder.hold(fx.X(k), Twc0[int(np.searchsorted(kf_ids, k))]))
    return graph
