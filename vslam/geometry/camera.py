"""Pinhole projection and the PnP solver setup shared by tracking, local mapping and loop verification."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from vslam.geometry.se3 import inv_T

if TYPE_CHECKING:
    import pycolmap

    from vslam.data.types import PinholeCamera


def project(T_world_cam: np.ndarray, X: np.ndarray, cam: PinholeCamera, min_depth: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (P,3) -> ideal pixels (P,2), depth (P,), mask in front of the camera and inside the image."""
    T = inv_T(T_world_cam)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy], axis=1)
    ok = (z > min_depth) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height - 1)
    return uv, z, ok


def pnp_setup(cam: PinholeCamera, max_error_px: float, seed: int, min_trials: int,
              max_trials: int) -> tuple[pycolmap.Camera, pycolmap.AbsolutePoseEstimationOptions]:
    """pycolmap pinhole camera of ideal pixels + seeded LO-RANSAC options for ``estimate_absolute_pose`` /
    ``estimate_and_refine_absolute_pose`` (one setup for tracking and loop verification; the fixed seed keeps runs
    deterministic)."""
    import pycolmap

    pycam = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height, params=[cam.fx, cam.fy, cam.cx, cam.cy])
    ao = pycolmap.AbsolutePoseEstimationOptions()
    ao.ransac.max_error = max_error_px
    ao.ransac.random_seed = seed
    ao.ransac.min_num_trials = min_trials
    ao.ransac.max_num_trials = max_trials
    return pycam, ao
