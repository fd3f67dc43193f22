"""INTERFACE STUB (being implemented): monocular two-view initialisation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class InitConfig:
    min_matches: int = 100  # fewer matches between the two views -> do not try
    ransac_px: float = 1.0  # inlier threshold for E/H, pixels
    min_parallax_deg: float = 1.0  # median triangulation angle needed to accept the initialisation
    min_points: int = 50  # triangulated inliers needed
    h_ratio: float = 0.45  # ORB-SLAM's model selection: homography when S_H / (S_H + S_F) > h_ratio
    seed: int = 0


@dataclass
class TwoViewResult:
    """T_cur_ref: (4,4) motion of the second view, scaled so the median depth of the points in the
    reference view is 1. pts_ref: (N,3) points in the reference camera frame (NaN where not
    triangulated); inliers: (N,) bool; model: "essential" or "homography"; parallax_deg: median."""

    T_cur_ref: np.ndarray
    pts_ref: np.ndarray
    inliers: np.ndarray
    model: str
    parallax_deg: float


def initialize_two_view(uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray, cfg: InitConfig = InitConfig()) -> TwoViewResult | None:
    """uv_ref, uv_cur: (N,2) matched ideal (undistorted) pixels; K (3,3). None when not well conditioned."""
    raise NotImplementedError
