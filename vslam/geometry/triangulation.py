"""Two-view triangulation with the checks a SLAM map needs before it accepts a point.

Method: the midpoint of the common perpendicular of the two viewing rays (Hartley & Zisserman,
"Multiple View Geometry", 2nd ed., §12.1; Beardsley et al. 1997), in closed form and fully
vectorised, so 2000 pairs cost about a millisecond. It is exact on noise-free data, needs no
SVD per point (unlike a per-point DLT), and degrades gracefully: parallel rays give NaN and a
False flag instead of an exception. Points are then checked the way ORB-SLAM's
``LocalMapping::CreateNewMapPoints`` does: positive depth in both cameras, enough parallax
between the rays, and a small reprojection error in both images.

Frames: ``T_world_c`` maps camera-frame points into the world, ``p_world = T_world_c @ p_c``
(see :mod:`vslam.geometry.se3`). Pixels are ideal (undistorted) and ``K`` is (3, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vslam.geometry.se3 import inv_T, skew

# Rays whose sin^2(angle) is below this are treated as parallel (angle < ~0.0006 deg): the
# midpoint is then numerically meaningless, and the point is left NaN.
_PARALLEL_SIN2 = 1e-13


@dataclass(frozen=True)
class TwoViewTriangulation:
    """Per-point triangulation results and the quantities the checks use, all shape (N,).

    pts_world: (N, 3) float64, world frame, same units as the pose translations (NaN for
    parallel rays); depth1/depth2: z in camera 1/2; parallax_deg: angle between the two rays at
    the point, degrees; err1_px/err2_px: reprojection error in image 1/2, pixels (NaN where the
    point is NaN or on a camera's image plane).
    """

    pts_world: np.ndarray
    depth1: np.ndarray
    depth2: np.ndarray
    parallax_deg: np.ndarray
    err1_px: np.ndarray
    err2_px: np.ndarray

    def ok(self, min_parallax_deg: float, max_reproj_px: float) -> np.ndarray:
        """(N,) bool: in front of both cameras, parallax >= threshold, reprojection <= threshold in
        both views. NaN anywhere compares False, so degenerate points are never accepted."""
        return (
            (self.depth1 > 0)
            & (self.depth2 > 0)
            & (self.parallax_deg >= min_parallax_deg)
            & (self.err1_px <= max_reproj_px)
            & (self.err2_px <= max_reproj_px)
        )


def fundamental(T_world_c1: np.ndarray, T_world_c2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(3,3) F with x2^T F x1 = 0 for ideal pixels x1 of view 1 and x2 of view 2, one camera K:
    F = K^-T [t]x R K^-1 with (R, t) = T_c2_c1 (H&Z §9.2)."""
    T_21 = inv_T(T_world_c2) @ T_world_c1
    Kinv = np.linalg.inv(K)
    return Kinv.T @ skew(T_21[:3, 3]) @ T_21[:3, :3] @ Kinv


def as_pixels(uv: np.ndarray, name: str) -> np.ndarray:
    """(N,2) float64 contiguous pixel array (empty -> (0,2)); ValueError naming ``name`` on a wrong shape."""
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    if uv.size == 0:
        return uv.reshape(0, 2)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {uv.shape}")
    return uv


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of two (N, k) arrays -> (N,)."""
    return np.einsum("ij,ij->i", a, b)


def _rays_world(T_world_c: np.ndarray, uv: np.ndarray, K_inv: np.ndarray) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) unit viewing directions in the world frame."""
    x = uv @ K_inv[:, :2].T + K_inv[:, 2]  # K^-1 [u, v, 1]^T for every row
    d = x @ T_world_c[:3, :3].T
    return d / np.sqrt(_dot(d, d))[:, None]


def _project_error(T_world_c: np.ndarray, pts_world: np.ndarray, uv: np.ndarray, K: np.ndarray):
    """Depth (N,) and pixel reprojection error (N,) of world points in one camera."""
    R, t = T_world_c[:3, :3], T_world_c[:3, 3]
    p_c = (pts_world - t) @ R  # R^T (p - t), row-wise
    z = p_c[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = p_c[:, :2] / z[:, None] @ K[:2, :2].T + K[:2, 2]
    r = proj - uv
    err = np.sqrt(_dot(r, r))
    return z, err


def triangulate_two_view(
    T_world_c1: np.ndarray, T_world_c2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, K: np.ndarray
) -> TwoViewTriangulation:
    """Midpoint triangulation of (N, 2) ideal pixel pairs plus the per-point check quantities.

    T_world_c1, T_world_c2: (4, 4) camera poses; uv1, uv2: (N, 2) pixels; K: (3, 3).
    Never raises on degenerate geometry: parallel rays give NaN points, and with identical poses
    the other rays meet at the camera centre (depth 0); either way every check fails.
    """
    T1 = np.asarray(T_world_c1, dtype=np.float64)
    T2 = np.asarray(T_world_c2, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    uv1, uv2 = as_pixels(uv1, "uv1"), as_pixels(uv2, "uv2")
    if uv1.shape != uv2.shape:
        raise ValueError(f"uv1 and uv2 must have the same shape, got {uv1.shape} and {uv2.shape}")
    K_inv = np.linalg.inv(K)
    c1, c2 = T1[:3, 3], T2[:3, 3]
    d1, d2 = _rays_world(T1, uv1, K_inv), _rays_world(T2, uv2, K_inv)

    # Closest points c1 + s d1 and c2 + u d2 (unit d): the normal equations
    #   s - a u = b.d1,  a s - u = b.d2  with a = d1.d2, b = c2 - c1,
    # have determinant -(1 - a^2) = -|d1 x d2|^2; the cross product keeps precision at small angles.
    b = c2 - c1
    a = _dot(d1, d2)
    bd1, bd2 = d1 @ b, d2 @ b
    cr = np.cross(d1, d2)
    sin2 = _dot(cr, cr)
    parallel = sin2 < _PARALLEL_SIN2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (bd1 - a * bd2) / sin2
        u = (a * bd1 - bd2) / sin2
    X = 0.5 * (c1 + s[:, None] * d1 + c2 + u[:, None] * d2)
    X[parallel] = np.nan

    z1, e1 = _project_error(T1, X, uv1, K)
    z2, e2 = _project_error(T2, X, uv2, K)
    r1, r2 = X - c1, X - c2
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_par = _dot(r1, r2) / np.sqrt(_dot(r1, r1) * _dot(r2, r2))
    parallax = np.degrees(np.arccos(np.clip(cos_par, -1.0, 1.0)))
    return TwoViewTriangulation(X, z1, z2, parallax, e1, e2)


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
    ok = in front of both cameras, parallax above the threshold, reprojection below it in both views.

    T_world_c1, T_world_c2: (4, 4) float, p_world = T_world_c @ p_c. uv1, uv2: (N, 2) float
    pixels, undistorted. K: (3, 3). pts_world is in the units of the pose translations, NaN for
    parallel rays, and only meaningful where ok is True (identical poses: every point is NaN or
    collapses onto the camera centre, and all of ok is False).
    Vectorised midpoint method.
    """
    tri = triangulate_two_view(T_world_c1, T_world_c2, uv1, uv2, K)
    return tri.pts_world, tri.ok(min_parallax_deg, max_reproj_px)
