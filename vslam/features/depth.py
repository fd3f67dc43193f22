"""Depth per keypoint, and its stereo-like form ``ur`` for the back end.

RGB-D reads the depth map at the keypoint; stereo matches left and right
keypoints by descriptor and triangulates with the calibrated extrinsics
(EuRoC is not rectified, KITTI and the synthetic rig are — one path serves
both). Both become ``ur = u - fx * b / z``: the x coordinate in a virtual
right camera ``b`` metres to the right, which is what the back end's stereo
factors expect, so RGB-D and stereo share every later step.
"""

from __future__ import annotations

import cv2
import numpy as np

from vslam.data.types import Calibration, PinholeCamera
from vslam.features.base import Features
from vslam.features.matching import match_mutual
from vslam.geometry.se3 import inv_T


def depth_rgbd(depth_map: np.ndarray | None, feats: Features, min_depth: float, max_depth: float) -> np.ndarray:
    """(N,) metres along z at each keypoint's raw pixel, NaN where missing or out of range."""
    z = np.full(len(feats), np.nan)
    if depth_map is None or len(feats) == 0:
        return z
    h, w = depth_map.shape[:2]
    ix = np.clip(np.round(feats.raw).astype(np.int64), 0, [w - 1, h - 1])
    d = depth_map[ix[:, 1], ix[:, 0]].astype(np.float64)
    ok = np.isfinite(d) & (d > min_depth) & (d < max_depth)
    z[ok] = d[ok]
    return z


def depth_stereo(
    left: Features, right: Features, calib: Calibration, min_depth: float, max_depth: float, max_px: float = 1.5,
    ratio: float = 0.8,
) -> np.ndarray:
    """(N,) depth in cam0 of each left keypoint from a left-right match, NaN where none.

    A match is kept only if the triangulated point lies in range in front of both
    cameras and reprojects within ``max_px`` in both (the epipolar check of an unrectified rig).
    """
    z = np.full(len(left), np.nan)
    cam1 = calib.cam1
    if cam1 is None or calib.T_cam0_cam1 is None or len(left) < 2 or len(right) < 2:
        return z
    m = match_mutual(left.desc, right.desc, ratio=ratio)
    if len(m) == 0:
        return z
    cam0: PinholeCamera = calib.cam0
    T_1_0 = inv_T(calib.T_cam0_cam1)
    P0 = cam0.K @ np.eye(4)[:3]
    P1 = cam1.K @ T_1_0[:3]
    a, b = left.uv[m[:, 0]], right.uv[m[:, 1]]
    X = cv2.triangulatePoints(P0, P1, a.T, b.T)
    with np.errstate(invalid="ignore", divide="ignore"):
        X = (X[:3] / X[3]).T
        X1 = X @ T_1_0[:3, :3].T + T_1_0[:3, 3]
        err0 = np.linalg.norm(cam0.project(X) - a, axis=1)
        err1 = np.linalg.norm(cam1.project(X1) - b, axis=1)
        ok = (X[:, 2] > min_depth) & (X[:, 2] < max_depth) & (X1[:, 2] > min_depth)
        ok &= (err0 < max_px) & (err1 < max_px)
    z[m[ok, 0]] = X[ok, 2]
    return z


def stereo_ur(uv: np.ndarray, depth: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """(N,) virtual right-camera x = u - fx * baseline / depth; NaN where depth is NaN."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return uv[:, 0] - fx * baseline / depth
