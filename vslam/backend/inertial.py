"""Visual-inertial local bundle adjustment: the visual factors of ``ba.py`` plus IMU preintegration factors.

Keys (``symbol_shorthand``): ``X(kf)`` = Pose3 T_world_body (body = IMU frame; the camera is attached
with ``T_body_cam`` as the visual factors' ``body_P_sensor``, so the IMU factor needs no lever-arm
approximation), ``V(kf)`` = body velocity in the world (m/s), ``B(kf)`` = ConstantBias (accel, gyro),
``L(pt)`` = world point. Gravity is whatever vector the preintegration params carry (``n_gravity``): the
SLAM world is the first keyframe's camera frame, not z up.

Graph: every visual observation of the window (``BAProblem``, poses given as T_world_cam and converted
here), one ``CombinedImuFactor(X(i), V(i), X(j), V(j), B(i), B(j), pim)`` between consecutive keyframes of
the *IMU chain* (the newest keyframes in time order; the bias random walk lives inside the factor), held
poses for the fixed keyframes, and priors on V and B of the chain's oldest keyframe; with line landmarks
(``BAProblem.lines``) their structureless window factor on the body poses (``line_window``, T_body_cam).
LM then chi2 classification and a second LM round without the visual outliers, as in
``local_bundle_adjustment``. Between the two, IMU factors wildly inconsistent with the visual poses
(``InertialBAConfig.max_imu_chi2``) are dropped and the first round solved again without them
(``ViResult.dropped`` tells the tracker, which restarts its IMU chain).

The chain's oldest state (why priors from marginal covariances): the window slides one keyframe at a
time, and the IMU factor that tied the oldest keyframe to its predecessor is dropped. A fixed-lag smoother
(``IncrementalFixedLagSmoother``) would marginalise it exactly, but it needs one persistent graph, while
local mapping edits the map between solves (point fusion, culling, outlier removal, keyframes leaving the
covisibility window), so the graph is rebuilt per keyframe like the visual BA. The two cheap treatments
of the oldest state were measured on synthetic stereo-inertial (``configs/synthetic_vio.yaml``, see
``vslam.tracking.vio``): ``"covariance"`` -- a Gaussian prior on V and B at the previous solve's estimate
with the previous solve's marginal covariance -- and ``"fix"`` -- V and B held at that estimate.
"covariance" was the more accurate for the price of one extra factorisation per keyframe, so it is the
default (docs/inertial.md, "Oldest state of the IMU chain"). The marginal prior double counts the visual information
that reached V/B through poses still in the window (it is an approximation of marginalisation, slightly
over-confident), which is why it is not used for the pose: the pose of the oldest keyframe is tied by
its own visual factors and the fixed covisible keyframes as in the visual BA.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from vslam.backend import factors as fx
from vslam.backend.ba import BackendConfig, BAProblem, BAResult, StereoCamera, _graph, _levenberg_marquardt
from vslam.backend.line_ba import camera_K_L, factors_within, line_chi2, line_estimates, line_terms
from vslam.backend.window import dense_window
from vslam.data.types import ImuSamples
from vslam.geometry.se3 import adjoint, inv_T


@dataclass(frozen=True)
class InertialBAConfig:
    """Settings of the visual-inertial local BA.

    chain: keyframes (newest, in time order) linked by IMU factors.
    oldest: treatment of the chain's oldest V/B state; measured choice in the module docstring.
    max_iterations / refine_iterations: LM iterations of the two rounds (IMU factors make the first
    solve after initialisation move further than a visual-only BA does, so a few more than visual BA).
    """

    chain: int = 10
    oldest: Literal["covariance", "fix"] = "covariance"
    max_iterations: int = 8
    refine_iterations: int = 4
    min_prior_sigma_v: float = 1e-3  # m/s: floor of the marginal prior (keeps it from freezing the state)
    min_prior_sigma_ba: float = 1e-4  # m/s^2
    min_prior_sigma_bg: float = 1e-5  # rad/s
    # IMU factor consistency: after the first LM round an IMU factor whose chi2 (15 dof) exceeds
    # max_imu_chi2 disagrees with the visual poses beyond any noise model (a corrupt stretch the sample gate cannot
    # see: a stuck axis, an offset burst, a clock jump); it is dropped and the window solved again without it, the
    # state after it held by loose priors (restart_sigma_v m/s, the bias sigmas m/s^2, rad/s) at its initial guess.
    # The threshold lies between the chi2 of clean runs' factors and that of a corrupt stretch, orders of
    # magnitude apart (docs/inertial.md, "IMU factor consistency"). The tracker turns the test off
    # monocular, where the map's scale comes from the IMU.
    max_imu_chi2: float = 1000.0
    restart_sigma_v: float = 1.0
    restart_sigma_ba: float = 0.1
    restart_sigma_bg: float = 0.01


@dataclass
class ImuChain:
    """The inertial part of a window (numpy in, numpy out).

    kf_ids: (K,) keyframe ids in time order, K >= 2, all in the BAProblem's poses.
    stamps: (K,) IMU-clock seconds. velocity: (K,3) world m/s of the body. bias: (K,6) accel (m/s^2) then gyro
    (rad/s). imu: samples covering [stamps[0], stamps[-1]]. params: gtsam preintegration params (from
    ``vslam.inertial.make_params``). T_body_cam: (4,4). prior_v / prior_b: covariances (3,3) / (6,6) of the
    oldest keyframe's velocity / bias prior, None = hold it (sigma 1e-6).
    """

    kf_ids: np.ndarray
    stamps: np.ndarray
    velocity: np.ndarray
    bias: np.ndarray
    imu: ImuSamples
    params: object
    T_body_cam: np.ndarray
    prior_v: np.ndarray | None = None
    prior_b: np.ndarray | None = None
    max_gap_s: float = 0.05  # preintegration's hole limit (``InertialConfig.max_gap_s``)


@dataclass
class ViResult:
    """Visual BA result (poses T_world_cam of the free keyframes, points, inliers) + inertial states.

    velocity / bias: kf id -> (3,) / (6,) for every chain keyframe. marginal: kf id -> (cov_v (3,3),
    cov_b (6,6)) for the chain's second keyframe (the next oldest), when computed.
    """

    ba: BAResult
    velocity: dict[int, np.ndarray] = field(default_factory=dict)
    bias: dict[int, np.ndarray] = field(default_factory=dict)
    marginal: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    ms: dict[str, float] = field(default_factory=dict)
    # IMU factors found inconsistent and left out: (kf i, kf j, chi2) in chain order
    dropped: list[tuple[int, int, float]] = field(default_factory=list)
    imu_chi2: dict[tuple[int, int], float] = field(default_factory=dict)  # every IMU factor's chi2 after round 1


def bias_object(b: np.ndarray) -> gtsam.imuBias.ConstantBias:
    b = np.asarray(b, dtype=np.float64).reshape(6)
    return gtsam.imuBias.ConstantBias(b[:3], b[3:])


def _floor_cov(cov: np.ndarray, floors: np.ndarray) -> np.ndarray:
    """Symmetrise and add floors^2 on the diagonal (a marginal of a well-observed state can be tiny)."""
    c = 0.5 * (cov + cov.T)
    return c + np.diag(np.asarray(floors, dtype=np.float64) ** 2)


def visual_inertial_bundle_adjustment(problem: BAProblem, chain: ImuChain, camera: StereoCamera,
                                      cfg: BackendConfig = BackendConfig(),
                                      icfg: InertialBAConfig = InertialBAConfig(),
                                      marginal_for: int | None = None) -> ViResult:
    """Optimise the window's free poses, all observed points and the chain's V/B (module docstring).

    marginal_for: keyframe id of the chain whose V/B marginal covariance to return (the next oldest).
    """
    from vslam.inertial.preintegration import preintegrate

    t0 = time.perf_counter()
    T_bc = np.asarray(chain.T_body_cam, dtype=np.float64)
    T_cb = inv_T(T_bc)
    win = dense_window(problem, camera, cfg)
    valid = np.isfinite(win.chi2(win.Twc0, win.P0, camera))
    idx = np.flatnonzero(valid)
    builder = fx.FactorBuilder(camera, cfg.huber_k, T_body_cam=T_bc)
    facs = builder.factors(win.kf[idx], win.pt[idx], win.meas[idx], win.stereo[idx], win.sigma[idx])
    chain_ids = [int(k) for k in chain.kf_ids]
    links = problem.usable_links()
    used_kf = sorted(set(win.kf_ids[np.unique(win.ik[idx])].tolist()) | set(chain_ids)
                     | {k for ln in links for k in (ln.a, ln.b)})
    used_pt = sorted(set(win.pt_ids[np.unique(win.ip[idx])].tolist()))
    held = [k for k in used_kf if k in problem.fixed] or used_kf[:1]
    values = gtsam.Values()
    for k in used_kf:
        values.insert(X(k), fx.pose3(problem.poses[k] @ T_cb))
    for j in used_pt:
        values.insert(L(j), np.asarray(problem.points[j], dtype=np.float64))
    other: list = [builder.hold(X(k), problem.poses[k] @ T_cb) for k in held]
    Ad_bc = adjoint(T_bc)  # a camera-frame link on body poses: T_b1_b2 = T_bc T_c1_c2 T_cb, its error turned by Ad(T_bc)
    other += [builder.between(ln.a, ln.b, T_bc @ ln.T_a_b @ T_cb, Ad_bc @ ln.cov @ Ad_bc.T) for ln in links]
    for i, k in enumerate(chain_ids):
        values.insert(V(k), np.asarray(chain.velocity[i], dtype=np.float64))
        values.insert(B(k), bias_object(chain.bias[i]))
    imu_facs = []
    for i in range(len(chain_ids) - 1):
        pim = preintegrate(chain.imu, float(chain.stamps[i]), float(chain.stamps[i + 1]), chain.params,
                           bias_object(chain.bias[i]), chain.max_gap_s)
        imu_facs.append(gtsam.CombinedImuFactor(X(chain_ids[i]), V(chain_ids[i]), X(chain_ids[i + 1]),
                                                V(chain_ids[i + 1]), B(chain_ids[i]), B(chain_ids[i + 1]), pim))
    other += imu_facs
    k0 = chain_ids[0]
    cov_v = chain.prior_v if chain.prior_v is not None else np.eye(3) * 1e-12
    cov_b = chain.prior_b if chain.prior_b is not None else np.eye(6) * 1e-12
    other.append(gtsam.PriorFactorVector(V(k0), np.asarray(chain.velocity[0], dtype=np.float64),
                                         gtsam.noiseModel.Gaussian.Covariance(cov_v)))
    other.append(gtsam.PriorFactorConstantBias(B(k0), bias_object(chain.bias[0]),
                                               gtsam.noiseModel.Gaussian.Covariance(cov_b)))
    line_facs, line_handle = [], None
    if problem.lines is not None:  # the window's lines on the body poses (``line_window`` with T_body_cam)
        line_facs, _, line_handle = line_terms(problem.lines, set(used_kf), camera_K_L(camera), cfg.huber_k, T_bc)
    graph = _graph(facs + other + line_facs)
    t1 = time.perf_counter()

    est, _, _ = _levenberg_marquardt(graph, values, icfg.max_iterations)
    chi2 = [2.0 * f.error(est) for f in imu_facs]
    bad = [i for i, c in enumerate(chi2) if c > icfg.max_imu_chi2]
    if bad:  # solve again from the initial guess (the first round was pulled by the bad factor) without them
        other = [f for f in other if not any(f is imu_facs[i] for i in bad)] + _restart_priors(chain, bad, icfg)
        graph = _graph(facs + other + line_facs)
        est, _, _ = _levenberg_marquardt(graph, values, icfg.max_iterations)
    Twc, P = _arrays(est, win, T_bc)
    keep = win.chi2(Twc, P, camera)[idx] <= win.thr[idx]
    if icfg.refine_iterations > 0 and keep.any() and not keep.all():
        kept_pts = set(win.pt[idx[keep]].tolist())
        start = gtsam.Values(est)
        for j in used_pt:
            if j not in kept_pts:  # no factor left: keeps its first-round value
                start.erase(L(j))
        graph = _graph([f for f, k in zip(facs, keep.tolist()) if k] + other + factors_within(line_facs, start))
        est2, _, _ = _levenberg_marquardt(graph, start, icfg.refine_iterations)
        est = gtsam.Values(est)
        est.update(est2)
    elif icfg.refine_iterations > 0:
        est, _, _ = _levenberg_marquardt(graph, est, icfg.refine_iterations)
    t2 = time.perf_counter()

    Twc, P = _arrays(est, win, T_bc)
    ba = BAResult(poses={}, points={int(j): P[i].copy() for i, j in enumerate(win.pt_ids.tolist())},
                  inliers=valid & (win.chi2(Twc, P, camera) <= win.thr))
    for i, k in enumerate(win.kf_ids.tolist()):
        if k not in problem.fixed and k not in held:
            ba.poses[int(k)] = Twc[i]
    if line_handle is not None:
        ba.lines = line_estimates(est, line_handle)
        cam_poses = {int(k): Twc[i] for i, k in enumerate(win.kf_ids.tolist())}
        for k in used_kf:  # chain keyframes without a point in the window
            cam_poses.setdefault(int(k), est.atPose3(X(k)).matrix() @ T_bc)
        ba.line_inliers = problem.lines.inliers(line_chi2(problem.lines, cam_poses, ba.lines, camera_K_L(camera)))
    out = ViResult(ba)
    out.imu_chi2 = {(chain_ids[i], chain_ids[i + 1]): c for i, c in enumerate(chi2)}
    out.dropped = [(chain_ids[i], chain_ids[i + 1], chi2[i]) for i in bad]
    for k in chain_ids:
        out.velocity[k] = np.asarray(est.atVector(V(k)), dtype=np.float64).reshape(3)
        out.bias[k] = np.asarray(est.atConstantBias(B(k)).vector(), dtype=np.float64).reshape(6)
    if marginal_for is not None and marginal_for in chain_ids:
        try:
            # A point left with one monocular observation is singular on its own; a 100 m prior on every
            # point adds no information that matters and keeps the joint system invertible.
            mg = gtsam.NonlinearFactorGraph(graph)
            weak = gtsam.noiseModel.Isotropic.Sigma(3, 100.0)
            for j in used_pt:
                if est.exists(L(j)):
                    mg.add(gtsam.PriorFactorPoint3(L(j), est.atPoint3(L(j)), weak))
            marg = gtsam.Marginals(mg, est)
            out.marginal[marginal_for] = (np.asarray(marg.marginalCovariance(V(marginal_for))),
                                          np.asarray(marg.marginalCovariance(B(marginal_for))))
        except RuntimeError:  # indeterminant system: no marginal, the caller falls back to its default prior
            pass
    t3 = time.perf_counter()
    out.ms = {"build": 1e3 * (t1 - t0), "optimize": 1e3 * (t2 - t1), "marginal": 1e3 * (t3 - t2)}
    return out


def _restart_priors(chain: ImuChain, bad: list[int], icfg: InertialBAConfig) -> list:
    """Loose priors on V and B of the state after each dropped IMU factor (at its initial guess): without the
    factor nothing before it ties them, and a chain segment with no prior on its first V/B is singular."""
    sv = gtsam.noiseModel.Isotropic.Sigma(3, icfg.restart_sigma_v)
    sb = gtsam.noiseModel.Diagonal.Sigmas(np.array([icfg.restart_sigma_ba] * 3 + [icfg.restart_sigma_bg] * 3))
    out: list = []
    for i in bad:
        k = int(chain.kf_ids[i + 1])
        out.append(gtsam.PriorFactorVector(V(k), np.asarray(chain.velocity[i + 1], dtype=np.float64), sv))
        out.append(gtsam.PriorFactorConstantBias(B(k), bias_object(chain.bias[i + 1]), sb))
    return out


def prior_covariances(marginal: tuple[np.ndarray, np.ndarray] | None, icfg: InertialBAConfig
                      ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(cov_v, cov_b) for the oldest chain state from a stored marginal, floored; (None, None) = hold it."""
    if marginal is None or icfg.oldest == "fix":
        return None, None
    cov_v, cov_b = marginal
    fb = [icfg.min_prior_sigma_ba] * 3 + [icfg.min_prior_sigma_bg] * 3
    return _floor_cov(cov_v, np.full(3, icfg.min_prior_sigma_v)), _floor_cov(cov_b, np.array(fb))


def initial_bias_covariance(sigma_acc: float, sigma_gyro: float) -> np.ndarray:
    """(6,6) diagonal prior covariance of the first bias state."""
    return np.diag([sigma_acc**2] * 3 + [sigma_gyro**2] * 3)


def _arrays(est: gtsam.Values, win, T_bc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,4,4) T_world_cam and (P,3) points at ``est``; variables not in it keep their initial value."""
    Twc, P = win.Twc0.copy(), win.P0.copy()
    for i, k in enumerate(win.kf_ids.tolist()):
        if est.exists(X(k)):
            Twc[i] = fx.pose_matrix(est.atPose3(X(k))) @ T_bc
    for i, j in enumerate(win.pt_ids.tolist()):
        if est.exists(L(j)):
            P[i] = est.atPoint3(L(j))
    return Twc, P
