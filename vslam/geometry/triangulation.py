"""INTERFACE STUB (being implemented): two-view triangulation with checks."""

from __future__ import annotations

import numpy as np


def triangulate_points(
    T_world_c1: np.ndarray,
    T_world_c2: np.ndarray,
    uv1: np.ndarray,
    uv2: np.ndarray,
    K: np.ndarray,
    min_parallax_deg: float = 1.0,
    max_reproj_px: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) ideal pixel pairs seen from two poses -> (pts_world (N,3), ok (N,) bool):
    ok = in front of both cameras, parallax above the threshold, reprojection below it in both views."""
    raise NotImplementedError
