"""3-D lines in Plücker coordinates, their projection, triangulation and minimal (orthonormal) form.

A line through world points p1, p2 is L = (n, d) with moment n = p1 x p2 and direction d = p2 - p1, so
d . n = 0 (seed 003, ch. 3; Hartley & Zisserman §3.2.2). L is homogeneous: (s n, s d) is the same line, and
the distance of the line from the origin is |n| / |d|. Arrays are (6,) or stacked (N, 6), columns n then d.

Transform (Bartoli & Sturm 2005, eq. 6): for p_b = R p_a + t,
``n_b = R n_a + [t]x R d_a,  d_b = R d_a``  (``line_transform_matrix`` is that 6x6 map).
Projection (Zhang et al., "Building a 3-D line-based map using stereo SLAM", 2015): with the camera-frame
moment n_c, the image line is ``l = K_L n_c`` with the line projection matrix
``K_L = [[fy, 0, 0], [0, fx, 0], [-fy cx, -fx cy, fx fy]]`` (= det(K) K^-T); only n enters, so points far
along the line cost nothing. Residuals are signed distances of segment end points to l, in pixels.
Orthonormal form (Bartoli & Sturm 2005): ``U = [n/|n|, d/|d|, n x d / |n x d|]`` in SO(3) and
``W = [[w1, -w2], [w2, w1]]`` in SO(2) with (w1, w2) = (|n|, |d|) / |(n, d)|: 4 DoF, updated by
``U <- U Exp(theta)``, ``W <- W Rot(phi)``, which can never leave the Plücker quadric.

Frames: ``T_world_c`` maps camera points into the world (vslam convention). Pixels are ideal (undistorted).
Pure numpy.
"""

from __future__ import annotations

import numpy as np

from vslam.geometry.se3 import inv_T, skew, so3_exp

# A line this close to the origin (|n|/|d| in metres) has an undefined moment direction; the orthonormal
# form then picks any unit vector perpendicular to d (the line through the origin is still exact: w1 = 0).
_MIN_MOMENT = 1e-12


def from_points(p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(N,3) or (3,) end points -> Plücker (N,6) or (6,): n = p1 x p2, d = p2 - p1 (not normalised)."""
    p1, p2 = np.asarray(p1, dtype=np.float64), np.asarray(p2, dtype=np.float64)
    return np.concatenate([np.cross(p1, p2), p2 - p1], axis=-1)


def normalize(L: np.ndarray) -> np.ndarray:
    """Scale so that |d| = 1 (then |n| is the distance from the origin); (..., 6) in and out."""
    L = np.asarray(L, dtype=np.float64)
    return L / np.linalg.norm(L[..., 3:], axis=-1, keepdims=True)


def constraint(L: np.ndarray) -> np.ndarray:
    """Klein-quadric residual d . n / (|n| |d| + tiny): 0 for a valid line; (...,) from (..., 6)."""
    L = np.asarray(L, dtype=np.float64)
    n, d = L[..., :3], L[..., 3:]
    return np.sum(n * d, axis=-1) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(d, axis=-1) + 1e-300)


def line_transform_matrix(T_b_a: np.ndarray) -> np.ndarray:
    """(4,4) T_b_a -> (6,6) H with L_b = H L_a (columns n, d)."""
    R, t = T_b_a[:3, :3], T_b_a[:3, 3]
    H = np.zeros((6, 6))
    H[:3, :3] = R
    H[:3, 3:] = skew(t) @ R
    H[3:, 3:] = R
    return H


def transform(L_a: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Lines (N,6) or (6,) in frame a -> frame b."""
    return np.asarray(L_a, dtype=np.float64) @ line_transform_matrix(T_b_a).T


def closest_point(L: np.ndarray) -> np.ndarray:
    """Point of the line closest to the origin, d x n / |d|^2; (..., 6) -> (..., 3)."""
    n, d = L[..., :3], L[..., 3:]
    return np.cross(d, n) / np.sum(d * d, axis=-1, keepdims=True)


def line_projection_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3,3) K_L with image line l = K_L n_c (see the module docstring)."""
    return np.array([[fy, 0.0, 0.0], [0.0, fx, 0.0], [-fy * cx, -fx * cy, fx * fy]])


def project(L_world: np.ndarray, T_world_cam: np.ndarray, K_L: np.ndarray) -> np.ndarray:
    """World lines (N,6)/(6,) seen from T_world_cam -> homogeneous image lines (N,3)/(3,) = K_L n_c."""
    Lc = transform(L_world, inv_T(T_world_cam))
    return Lc[..., :3] @ K_L.T


def point_line_distance(uv: np.ndarray, l: np.ndarray) -> np.ndarray:
    """Signed pixel distance of points uv (..., 2) to lines l (..., 3) (broadcast): (l . [u, v, 1]) / |l[:2]|."""
    uv, l = np.asarray(uv, dtype=np.float64), np.asarray(l, dtype=np.float64)
    return (l[..., 0] * uv[..., 0] + l[..., 1] * uv[..., 1] + l[..., 2]) / np.hypot(l[..., 0], l[..., 1])


def segment_distances(segs: np.ndarray, l: np.ndarray) -> np.ndarray:
    """(N,4) segments (u1, v1, u2, v2) and (N,3) lines -> (N,2) signed end-point distances, pixels."""
    segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    l = np.asarray(l, dtype=np.float64).reshape(-1, 3)
    return np.stack([point_line_distance(segs[:, :2], l), point_line_distance(segs[:, 2:], l)], axis=1)


def image_line(segs: np.ndarray) -> np.ndarray:
    """(N,4) segments -> (N,3) homogeneous lines through both end points (x1 x x2)."""
    segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    one = np.ones((len(segs), 1))
    return np.cross(np.hstack([segs[:, :2], one]), np.hstack([segs[:, 2:], one]))


def backproject_planes(segs: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,4) segments -> (N,4) world planes pi = (a, b, c, e), a x + b y + c z + e = 0, through the camera
    centre and the segment (camera-frame normal K^T l, unit length)."""
    nc = image_line(segs) @ K
    nc /= np.linalg.norm(nc, axis=1, keepdims=True)
    R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
    nw = nc @ R.T
    return np.hstack([nw, -(nw @ C)[:, None]])


def triangulate_planes(
    segs1: np.ndarray, segs2: np.ndarray, T_world_c1: np.ndarray, T_world_c2: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Two-view line triangulation by intersecting the back-projected planes (H&Z §12.6).

    segs1, segs2: (N,4) matched segments in view 1/2 (ideal pixels). Returns world lines (N,6) with |d| = 1
    and the (N,) sine of the angle between the two planes (small = ill-conditioned: the line lies near
    the epipolar plane, or the baseline is tiny).
    For planes (n_i, e_i) a point p of the line has n_i . p = -e_i, so d = n1 x n2 and
    n = p x d = e1 n2 - e2 n1 (the rows of the dual Plücker matrix pi1 pi2^T - pi2 pi1^T).
    """
    p1 = backproject_planes(segs1, T_world_c1, K)
    p2 = backproject_planes(segs2, T_world_c2, K)
    d = np.cross(p1[:, :3], p2[:, :3])
    n = p1[:, 3:4] * p2[:, :3] - p2[:, 3:4] * p1[:, :3]
    sin = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        L = np.hstack([n, d]) / sin[:, None]
    return L, sin


def from_depth(segs: np.ndarray, z1: np.ndarray, z2: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,4) segments with end-point depths z1, z2 (N,) metres (RGB-D, or stereo disparity) -> world
    lines (N,6), |d| = 1. The end points themselves are ``end_points_from_depth``."""
    a, b = end_points_from_depth(segs, z1, z2, T_world_cam, K)
    return normalize(from_points(a, b))


def end_points_from_depth(segs, z1, z2, T_world_cam, K) -> tuple[np.ndarray, np.ndarray]:
    """(N,4) segments and end-point depths -> two (N,3) world end points."""
    segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    Ki = np.linalg.inv(K)
    one = np.ones((len(segs), 1))
    a = (np.hstack([segs[:, :2], one]) @ Ki.T) * np.asarray(z1, dtype=np.float64)[:, None]
    b = (np.hstack([segs[:, 2:], one]) @ Ki.T) * np.asarray(z2, dtype=np.float64)[:, None]
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    return a @ R.T + t, b @ R.T + t


def end_rays(segs: np.ndarray, K_L: np.ndarray) -> np.ndarray:
    """(N,4) ideal segments -> (N,2,3) viewing rays (x, y, 1) of their end points, the intrinsics read off
    the line projection matrix ``K_L`` (fx = K_L[1,1], fy = K_L[0,0], -fy cx, -fx cy in its last row)."""
    fx, fy = K_L[1, 1], K_L[0, 0]
    cx, cy = -K_L[2, 0] / fy, -K_L[2, 1] / fx
    uv = np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2)
    return np.concatenate([(uv - [cx, cy]) / [fx, fy], np.ones(uv.shape[:2] + (1,))], axis=2)


def inverse_depth(n_c: np.ndarray, d_c: np.ndarray, rays: np.ndarray, jac: bool = False):
    """Inverse depth 1/z of the camera-frame line (n_c, d_c) (N,3) each where the viewing ray r = (x, y, 1)
    of an image point passes closest to it; rays (N,k,3) -> rho (N,k) and, with jac, d rho/d n_c and
    d rho/d d_c (N,k,3) each.

    Why: an RGB-D end point measures its depth, and this is the depth the line predicts there. With
    m = r x d, rho = |m|^2 / (m . n): for X = s r on the line, n = X x d = s m, so rho = 1/s. A ray along
    the line (m -> 0) has no depth: the caller drops end points whose projection is that degenerate.
    """
    m = _cross3(rays, d_c[:, None, :])
    mm = np.sum(m * m, axis=2)
    mn = np.einsum("nki,ni->nk", m, n_c)
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = mm / mn
        if not jac:
            return rho, None, None
        d_n = -(rho / mn)[:, :, None] * m
        d_m = (2.0 / mn)[:, :, None] * m - (rho / mn)[:, :, None] * n_c[:, None, :]
    # m = [r]x d, so d rho / d d = d_m^T [r]x = (d_m x r)^T
    return rho, d_n, _cross3(d_m, rays)


def clip_to_segment(L_world: np.ndarray, segs: np.ndarray, T_world_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of the infinite lines L (N,6) nearest to the viewing rays of the segments' end points (N,4)
    -> two (N,3) world points: the finite extent a map line gets for export (PLY line set)."""
    L = normalize(np.asarray(L_world, dtype=np.float64).reshape(-1, 6))
    segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
    C = T_world_cam[:3, 3]
    P0, D = closest_point(L), L[:, 3:]
    Ki = np.linalg.inv(K)
    out = []
    for cols in (slice(0, 2), slice(2, 4)):
        ray = (np.hstack([segs[:, cols], np.ones((len(segs), 1))]) @ Ki.T) @ T_world_cam[:3, :3].T
        # closest point of P0 + s D to C + r ray: minimise |P0 + s D - C - r ray|^2 over (s, r)
        w = P0 - C
        a, b, c = np.sum(D * D, 1), np.sum(D * ray, 1), np.sum(ray * ray, 1)
        dd, e = np.sum(D * w, 1), np.sum(ray * w, 1)
        den = a * c - b * b
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(np.abs(den) > 1e-12, (b * e - c * dd) / den, -dd / a)
        out.append(P0 + s[:, None] * D)
    return out[0], out[1]


# -- orthonormal representation ------------------------------------------------------------------------------


def to_orthonormal(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plücker (6,) -> (U (3,3) rotation, w (2,) = (cos, sin) of W's angle) (Bartoli & Sturm 2005).
    Stacked input (N,6) gives (N,3,3) and (N,2) (vectorised: local BA converts ~100 lines per call)."""
    L = np.asarray(L, dtype=np.float64)
    one = L.ndim == 1
    L = L.reshape(-1, 6)
    n, d = L[:, :3], L[:, 3:]
    nn, dn = np.linalg.norm(n, axis=1), np.linalg.norm(d, axis=1)
    u2 = d / dn[:, None]
    through_origin = nn <= _MIN_MOMENT * dn
    u1 = n / np.where(through_origin, 1.0, nn)[:, None]
    u1 = u1 - np.sum(u1 * u2, axis=1, keepdims=True) * u2  # re-impose d . n = 0 against rounding
    if through_origin.any():  # any unit vector perpendicular to d serves as the moment direction
        a = np.eye(3)[np.argmin(np.abs(u2[through_origin]), axis=1)]
        u1[through_origin] = _cross3(u2[through_origin], a)
    u1 /= np.linalg.norm(u1, axis=1, keepdims=True)
    U = np.stack([u1, u2, _cross3(u1, u2)], axis=2)
    w = np.stack([nn, dn], axis=1) / np.hypot(nn, dn)[:, None]
    return (U[0], w[0]) if one else (U, w)


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis, broadcast (np.cross's overhead per call dominates at these sizes;
    docs/speed.md)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def from_orthonormal(U: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(U, w) -> Plücker (6,) = (w1 u1, w2 u2), so |n|^2 + |d|^2 = 1."""
    return np.concatenate([w[0] * U[:, 0], w[1] * U[:, 1]])


def orthonormal_retract(U: np.ndarray, w: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the 4-DoF update delta = (theta (3,), phi): U Exp(theta), W Rot(phi). Always a valid line."""
    c, s = np.cos(delta[3]), np.sin(delta[3])
    return U @ so3_exp(delta[:3]), np.array([w[0] * c - w[1] * s, w[1] * c + w[0] * s])


def orthonormal_jacobian(U: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(6,4) d L / d(theta, phi) of ``from_orthonormal`` at the update above (theta = 0, phi = 0).

    d u_i / d theta = -U [e_i]x (right perturbation of U); d (w1, w2) / d phi = (-w2, w1).
    """
    J = np.zeros((6, 4))
    J[:3, :3] = -w[0] * U @ skew(np.array([1.0, 0.0, 0.0]))
    J[3:, :3] = -w[1] * U @ skew(np.array([0.0, 1.0, 0.0]))
    J[:3, 3] = -w[1] * U[:, 0]
    J[3:, 3] = w[0] * U[:, 1]
    return J
