"""Pose-graph optimisation (GTSAM): keyframe poses tied by relative-pose edges, after a loop closure.

ORB-SLAM's essential-graph step: every keyframe is a ``Pose3`` variable
``X(kf_id)`` (T_world_cam); each edge (i, j, T_i_j) is a ``BetweenFactorPose3``
measuring T_i_j = inv(T_world_i) T_world_j. Odometry / covisibility edges take
their measurement from the poses *before* the correction (the local geometry
the tracker and local BA got right); a loop edge comes from geometric
verification. All edges share one diagonal noise model (optionally inside a
Cauchy kernel, off by default: see ``PoseGraphConfig.cauchy_k``). The ``fixed`` keyframes (at least the gauge) are held
by a tight prior.

Poses are SE3 in ``optimize_pose_graph``: this serves RGB-D and stereo, where the
scale is observed. A monocular loop also closes a scale drift: ``optimize_sim3_graph``
(ORB-SLAM's OptimizeEssentialGraph with Sim3) makes every keyframe a
``Similarity3`` -- camera to world, X_w = s R X_c + t -- tied by
``BetweenFactorSimilarity3`` edges; the odometry edges carry scale 1, the loop
edges the scale the verification measured. GTSAM's ``Similarity3(R, t, s)``
maps p to s (R p + t), so its t is ours / s (``sim_matrix`` / ``sim_parts``).
``vslam.loop.closing.LoopCloser.correct_sim3`` calls it for monocular loops.
Measured on the synthetic 2-loop lighting route seen by one camera (bench rows
room-2loops-light-mono*) and on constructed maps (tests/backend/test_pose_graph.py,
tests/loop/test_sim3_closing.py): it removes the scale drift the SE3 graph leaves (docs/backend.md,
"Pose graph").
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vslam.backend import factors as fx


@dataclass(frozen=True)
class PoseEdge:
    """Relative pose T_i_j (4,4) = inv(T_world_i) @ T_world_j; ``loop``: from a loop closure (for reports)."""

    i: int
    j: int
    T_i_j: np.ndarray
    loop: bool = False


@dataclass(frozen=True)
class PoseGraphConfig:
    sigma_rot: float = 0.01  # rad, per edge and axis
    sigma_trans: float = 0.01  # metres, per edge and axis
    # Robust kernel width in sigmas; 0 = plain least squares (the default, as ORB-SLAM's essential graph).
    # A loop edge starts many sigmas off, so a Cauchy kernel down-weights exactly the edge that should pull,
    # and LM stops in a half-corrected state, worse than without the loop even with the true loop pose
    # (docs/backend.md, "Pose graph"). Wrong loops are kept out by verification instead.
    cauchy_k: float = 0.0
    max_iterations: int = 50


def _optimize(init: dict[int, np.ndarray], edges: list[tuple[int, int, np.ndarray]], fixed: set[int],
              cfg: PoseGraphConfig, sigmas: np.ndarray, to_gtsam, from_gtsam, between, prior, at
              ) -> tuple[dict[int, np.ndarray], float, float]:
    """The graph both pose graphs share: ``between`` factors on (i, j, measurement) edges between ids of ``init``,
    the ``fixed`` ids (else the lowest) held by a tight ``prior``, LM; fixed and unconnected ids come back as given.
    to_gtsam / from_gtsam / at: the variable type's conversions and ``Values`` accessor."""
    graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    if cfg.cauchy_k > 0:
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.cauchy_k), noise)
    used: set[int] = set()
    for i, j, M in edges:
        if i in init and j in init and i != j:
            graph.add(between(fx.X(i), fx.X(j), to_gtsam(M), noise))
            used.update((i, j))
    anchors = sorted(fixed & set(init)) or [min(init)]
    used.update(anchors)
    hold = gtsam.noiseModel.Isotropic.Sigma(len(sigmas), 1e-6)
    for k in anchors:
        graph.add(prior(fx.X(k), to_gtsam(init[k]), hold))
    values = gtsam.Values()
    for k, M in init.items():
        if k in used:  # a keyframe without edges has nothing to move it (and would make LM singular)
            values.insert(fx.X(k), to_gtsam(M))
    est = gtsam.LevenbergMarquardtOptimizer(graph, values, fx.lm_params(cfg.max_iterations)).optimize()
    out = {k: (from_gtsam(at(est, fx.X(k))) if k in used and k not in anchors else np.array(M, dtype=np.float64))
           for k, M in init.items()}
    return out, float(graph.error(values)), float(graph.error(est))


def optimize_pose_graph(poses: dict[int, np.ndarray], edges: list[PoseEdge], fixed: set[int],
                        cfg: PoseGraphConfig = PoseGraphConfig()) -> tuple[dict[int, np.ndarray], float, float]:
    """-> (optimised T_world_cam per keyframe id, initial error, final error).

    poses: initial guesses (4,4); edges between ids of ``poses`` (others are ignored); fixed: ids held.
    Fixed keyframes come back bit-identical; with no fixed id the lowest id anchors the gauge.
    """
    sig = np.r_[np.full(3, cfg.sigma_rot), np.full(3, cfg.sigma_trans)]  # GTSAM Pose3 tangent: rotation first
    return _optimize(poses, [(e.i, e.j, e.T_i_j) for e in edges], fixed, cfg, sig, fx.pose3, fx.pose_matrix,
                     gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3, gtsam.Values.atPose3)


@dataclass(frozen=True)
class SimEdge:
    """Relative similarity S_i_j (4,4: [[s R, t], [0, 1]]) = inv(S_world_i) @ S_world_j; ``loop``: from a loop."""

    i: int
    j: int
    S_i_j: np.ndarray
    loop: bool = False


def sim_matrix(T: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(4,4) similarity [[scale R, t], [0, 1]] from a rigid T = (R, t)."""
    S = np.array(T, dtype=np.float64, copy=True)
    S[:3, :3] *= scale
    return S


def sim_parts(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) of a (4,4) similarity [[s R, t], [0, 1]]."""
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    return S[:3, :3] / s, S[:3, 3].copy(), s


def _to_gtsam(S: np.ndarray) -> gtsam.Similarity3:
    R, t, s = sim_parts(S)
    return gtsam.Similarity3(gtsam.Rot3(R), t / s, s)


def _from_gtsam(G: gtsam.Similarity3) -> np.ndarray:
    out = np.eye(4)
    s = float(G.scale())
    out[:3, :3] = s * G.rotation().matrix()
    out[:3, 3] = s * np.asarray(G.translation())
    return out


def optimize_sim3_graph(sims: dict[int, np.ndarray], edges: list[SimEdge], fixed: set[int],
                        cfg: PoseGraphConfig = PoseGraphConfig(), sigma_scale: float = 0.01
                        ) -> tuple[dict[int, np.ndarray], float, float]:
    """-> (optimised camera-to-world similarity (4,4) per keyframe id, initial error, final error).

    sims: initial S_world_cam per keyframe (rigid poses are similarities of scale 1); edges as SimEdge;
    fixed: ids held (the lowest id when empty). sigma_scale: per-edge std of log-scale.
    """
    # Similarity3 tangent: rotation (3), translation (3), log-scale (1)
    sig = np.r_[np.full(3, cfg.sigma_rot), np.full(3, cfg.sigma_trans), sigma_scale]
    return _optimize(sims, [(e.i, e.j, e.S_i_j) for e in edges], fixed, cfg, sig, _to_gtsam, _from_gtsam,
                     gtsam.BetweenFactorSimilarity3, gtsam.PriorFactorSimilarity3, gtsam.Values.atSimilarity3)
