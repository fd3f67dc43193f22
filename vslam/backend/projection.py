"""Numpy stereo-pinhole measurement model shared by local BA (classification) and pose-only refinement.

The model is the one GTSAM's ``StereoCamera(Pose3(T_world_cam), Cal3_S2Stereo(fx, fy, 0, cx, cy, b))``
implements (checked in ``tests/backend/test_ba.py``): with ``p = T_cam_world @ p_world``,

    uL = fx * X / Z + cx,   v = fy * Y / Z + cy,   uR = fx * (X - b) / Z + cx = uL - fx * b / Z

A mono measurement is (uL, v) only; its ``ur`` is NaN. With ``camera.disparity_sigma > 0`` (RGB-D) the third
whitened residual is the disparity error (e_uL - e_uR) / disparity_sigma instead of e_uR / sigma, the same
model as the correlated (uL, uR, v) covariance of ``factors.FactorBuilder``. Nothing here imports GTSAM.
"""

from __future__ import annotations

import numpy as np

from vslam.geometry.se3 import inv_T

#: A point closer than this to the camera plane (metres, camera z) is "behind the camera" (ORB-SLAM uses z > 0).
MIN_DEPTH = 1e-6


def transform_points(T_cam_world: np.ndarray, pts_world: np.ndarray) -> np.ndarray:
    """(4,4) T_cam_world, (N,3) world points (metres) -> (N,3) camera-frame points (metres)."""
    return pts_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]


def project_cam(pts_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, baseline: float) -> np.ndarray:
    """(N,3) camera-frame points -> (N,3) predicted (uL, v, uR) pixels; rows with z <= 0 are garbage, mask them."""
    X, Y, Z = pts_cam[:, 0], pts_cam[:, 1], pts_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        iz = 1.0 / Z
    uL = fx * X * iz + cx
    return np.stack([uL, fy * Y * iz + cy, uL - fx * baseline * iz], axis=1)


def project_stereo(T_world_cam: np.ndarray, pts_world: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points into a stereo-like camera.

    T_world_cam: (4,4) camera pose in the world; pts_world: (N,3) metres; camera: ``StereoCamera``.
    Returns uv (N,2) left-image pixels, ur (N,) virtual-right x pixels (meaningless when baseline == 0),
    depth (N,) camera z in metres (<= 0: behind the camera, uv/ur undefined).
    """
    pts_world = np.asarray(pts_world, dtype=np.float64).reshape(-1, 3)
    T_cam_world = inv_T(T_world_cam)
    pc = transform_points(T_cam_world, pts_world)
    pred = project_cam(pc, camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
    return pred[:, :2], pred[:, 2], pc[:, 2]


def backproject_cam(meas: np.ndarray, fx: float, fy: float, cx: float, cy: float, baseline: float) -> np.ndarray:
    """Inverse of ``project_cam``: (N,3) stereo measurements (uL, v, uR) with uL > uR -> (N,3) camera-frame
    points (metres) that project exactly onto them."""
    uL, v, uR = np.asarray(meas, dtype=np.float64).reshape(-1, 3).T
    z = fx * baseline / (uL - uR)
    return np.stack([(uL - cx) * z / fx, (v - cy) * z / fy, z], axis=1)


def measurement_matrix(uv: np.ndarray, ur: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) uv, (N,) ur -> (N,3) measurement rows (uL, v, uR with 0 for mono) and (N,) bool stereo mask."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    ur = np.asarray(ur, dtype=np.float64).reshape(-1)
    stereo = np.isfinite(ur)
    z = np.empty((uv.shape[0], 3))
    z[:, :2] = uv
    z[:, 2] = np.where(stereo, ur, 0.0)
    return z, stereo


def whitened_sq_errors(
    pts_cam: np.ndarray, meas: np.ndarray, stereo: np.ndarray, sigma: np.ndarray | float, camera
) -> tuple[np.ndarray, np.ndarray]:
    """Unrobust whitened squared reprojection errors (chi2 statistics) of N observations.

    pts_cam: (N,3) camera-frame points; meas: (N,3) from ``measurement_matrix``; stereo: (N,) bool;
    sigma: pixel std, scalar or (N,). Returns (N,) chi2 values (inf where the point is behind the
    camera or anything is NaN) and the (N,3) residuals predicted - measured (uR column 0 for mono).
    """
    pred = project_cam(pts_cam, camera.fx, camera.fy, camera.cx, camera.cy, camera.baseline)
    r = pred - meas
    r[:, 2] = np.where(stereo, r[:, 2], 0.0)
    sd = float(camera.disparity_sigma)
    if sd > 0:
        chi2 = (r[:, 0] ** 2 + r[:, 1] ** 2) / np.square(sigma) + np.where(stereo, (r[:, 0] - r[:, 2]) / sd, 0.0) ** 2
    else:
        chi2 = np.einsum("ij,ij->i", r, r) / np.square(sigma)
    bad = ~(pts_cam[:, 2] > MIN_DEPTH) | ~np.isfinite(chi2)
    chi2[bad] = np.inf
    return chi2, r


def chi2_thresholds(stereo: np.ndarray, chi2_mono: float, chi2_stereo: float) -> np.ndarray:
    """(N,) bool stereo mask -> (N,) chi2 threshold per observation (2 or 3 degrees of freedom)."""
    return np.where(stereo, chi2_stereo, chi2_mono)

