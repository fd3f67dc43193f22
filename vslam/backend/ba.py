"""INTERFACE STUB (being implemented): local bundle adjustment and pose-only refinement.

Measurements are *ideal* (undistorted) pixels of the left camera with the
pinhole K of cam0. A stereo-like measurement adds ``ur``, the x coordinate the
point would have in a virtual right camera shifted by ``baseline`` along +x
(stereo: the matched right keypoint, rectified; RGB-D: ``u - fx * baseline /
depth`` with a virtual baseline), NaN for a monocular measurement.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class BackendConfig:
    pixel_sigma: float = 1.0  # std of a keypoint measurement, pixels
    huber_k: float = 1.345  # Huber threshold in sigmas (robust loss on every visual factor)
    chi2_mono: float = 5.991  # 95 % of chi2(2): an observation above this after BA is an outlier
    chi2_stereo: float = 7.815  # 95 % of chi2(3)
    max_iterations: int = 10  # Levenberg-Marquardt iterations of local BA
    rgbd_virtual_baseline: float = 0.08  # metres; RGB-D depth as a virtual stereo pair (ORB-SLAM2 uses bf/fx ~ 0.08)


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
    obs_kf, obs_pt: (M,) int ids of each observation's keyframe and point.
    obs_uv: (M,2) ideal pixels; obs_ur: (M,) virtual right x, NaN for mono.
    """

    poses: dict[int, np.ndarray]
    fixed: set[int]
    points: dict[int, np.ndarray]
    obs_kf: np.ndarray
    obs_pt: np.ndarray
    obs_uv: np.ndarray
    obs_ur: np.ndarray


@dataclass
class BAResult:
    poses: dict[int, np.ndarray]  # optimized poses of the non-fixed keyframes (fixed ones unchanged)
    points: dict[int, np.ndarray]
    inliers: np.ndarray  # (M,) bool, chi2 test after optimisation
    iterations: int = 0
    initial_error: float = float("nan")
    final_error: float = float("nan")
    ms: dict[str, float] = field(default_factory=dict)


def local_bundle_adjustment(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig = BackendConfig()) -> BAResult:
    raise NotImplementedError


def optimize_pose(
    T_world_cam: np.ndarray,
    pts_world: np.ndarray,
    uv: np.ndarray,
    ur: np.ndarray,
    camera: StereoCamera,
    cfg: BackendConfig = BackendConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Pose-only refinement with fixed points: -> (T_world_cam (4,4), inliers (N,) bool)."""
    raise NotImplementedError
