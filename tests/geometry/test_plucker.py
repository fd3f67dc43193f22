"""Plücker-line algebra: the constraint, transforms, projection, triangulation, orthonormal form."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.geometry import plucker as pl
from vslam.geometry.se3 import inv_T, make_T, so3_exp

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
K_L = pl.line_projection_matrix(500.0, 480.0, 320.0, 240.0)


def _lines(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n segments 3-6 m in front of the identity camera."""
    a = np.column_stack([rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(3.0, 6.0, n)])
    b = a + rng.normal(0.0, 0.7, (n, 3))
    b[:, 2] = np.clip(b[:, 2], 3.0, 6.0)
    return a, b


def _pose(rng: np.random.Generator, deg: float = 5.0, m: float = 0.3) -> np.ndarray:
    return make_T(so3_exp(rng.normal(0, np.deg2rad(deg), 3)), rng.normal(0, m, 3))


def _project_pts(T_world_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = X @ inv_T(T_world_cam)[:3, :3].T + inv_T(T_world_cam)[:3, 3]
    return (Xc @ K.T)[:, :2] / Xc[:, 2:]


def test_constraint_kept_by_construction_and_transform():
    rng = np.random.default_rng(0)
    a, b = _lines(rng, 50)
    L = pl.from_points(a, b)
    assert np.abs(pl.constraint(L)).max() < 1e-14
    Lb = pl.transform(L, _pose(rng, 30.0, 2.0))
    assert np.abs(pl.constraint(Lb)).max() < 1e-13


def test_transform_round_trip_and_matches_transformed_points():
    rng = np.random.default_rng(1)
    a, b = _lines(rng, 20)
    T = _pose(rng, 20.0, 1.0)
    L = pl.from_points(a, b)
    Lb = pl.transform(L, T)
    ta, tb = a @ T[:3, :3].T + T[:3, 3], b @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(Lb, pl.from_points(ta, tb), atol=1e-12)
    np.testing.assert_allclose(pl.transform(Lb, inv_T(T)), L, atol=1e-12)


def test_projection_passes_through_projected_points():
    rng = np.random.default_rng(2)
    a, b = _lines(rng, 30)
    T_wc = _pose(rng)
    L = pl.from_points(a, b)
    l = pl.project(L, T_wc, K_L)
    for s in (0.0, 0.3, 1.0, 2.5):  # any point of the infinite line, also beyond the segment
        uv = _project_pts(T_wc, a + s * (b - a))
        assert np.abs(pl.point_line_distance(uv, l)).max() < 1e-9
    # and the line is the one through the two projected end points (up to scale)
    segs = np.hstack([_project_pts(T_wc, a), _project_pts(T_wc, b)])
    li = pl.image_line(segs)
    cos = np.abs(np.sum(li * l, 1)) / (np.linalg.norm(li, axis=1) * np.linalg.norm(l, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-12)


def test_point_line_distance_in_pixels():
    l = np.array([0.0, 1.0, -100.0])  # v = 100, scaled arbitrarily below
    np.testing.assert_allclose(pl.point_line_distance(np.array([[5.0, 103.0], [7.0, 96.0]]), 7.3 * l), [3.0, -4.0])


def test_two_view_triangulation_noiseless_equals_truth():
    rng = np.random.default_rng(3)
    a, b = _lines(rng, 40)
    T1, T2 = np.eye(4), make_T(so3_exp(np.array([0.02, -0.05, 0.01])), np.array([0.4, 0.1, 0.05]))
    segs1 = np.hstack([_project_pts(T1, a), _project_pts(T1, b)])
    # view 2 sees other end points along the same lines: triangulation must not need point correspondences
    segs2 = np.hstack([_project_pts(T2, a + 0.2 * (b - a)), _project_pts(T2, b + 0.3 * (b - a))])
    L, sin = pl.triangulate_planes(segs1, segs2, T1, T2, K)
    ok = sin > 0.01
    assert ok.sum() >= 35
    truth = pl.normalize(pl.from_points(a, b))
    sign = np.sign(np.sum(L[:, 3:] * truth[:, 3:], axis=1))[:, None]
    np.testing.assert_allclose((L * sign)[ok], truth[ok], atol=1e-8)


def test_from_depth_and_clip_recover_end_points():
    rng = np.random.default_rng(4)
    a, b = _lines(rng, 10)
    T = _pose(rng)
    segs = np.hstack([_project_pts(T, a), _project_pts(T, b)])
    Tcw = inv_T(T)
    z1, z2 = (a @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2], (b @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2]
    L = pl.from_depth(segs, z1, z2, T, K)
    np.testing.assert_allclose(L, pl.normalize(pl.from_points(a, b)), atol=1e-10)
    pa, pb = pl.clip_to_segment(L, segs, T, K)
    np.testing.assert_allclose(pa, a, atol=1e-8)
    np.testing.assert_allclose(pb, b, atol=1e-8)


def test_orthonormal_round_trip_and_update_stays_valid():
    rng = np.random.default_rng(5)
    a, b = _lines(rng, 20)
    for L in pl.from_points(a, b):
        U, w = pl.to_orthonormal(L)
        np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
        L1 = pl.from_orthonormal(U, w)
        np.testing.assert_allclose(L1 / np.linalg.norm(L1), L / np.linalg.norm(L), atol=1e-12)
        for _ in range(5):
            U, w = pl.orthonormal_retract(U, w, rng.normal(0.0, 0.5, 4))
            L2 = pl.from_orthonormal(U, w)
            assert abs(pl.constraint(L2)) < 1e-12
            np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
            assert abs(np.linalg.norm(L2) - 1.0) < 1e-12


def test_orthonormal_jacobian_matches_numeric():
    rng = np.random.default_rng(6)
    a, b = _lines(rng, 3)
    for L in pl.from_points(a, b):
        U, w = pl.to_orthonormal(L)
        J = pl.orthonormal_jacobian(U, w)
        Jn = np.zeros((6, 4))
        h = 1e-6
        for i in range(4):
            e = np.zeros(4)
            e[i] = h
            Jn[:, i] = (pl.from_orthonormal(*pl.orthonormal_retract(U, w, e))
                        - pl.from_orthonormal(*pl.orthonormal_retract(U, w, -e))) / (2 * h)
        np.testing.assert_allclose(J, Jn, atol=1e-9)


def test_line_through_origin_has_valid_orthonormal_form():
    U, w = pl.to_orthonormal(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 2.0]))
    np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
    assert w[0] == pytest.approx(0.0) and w[1] == pytest.approx(1.0)


def test_inverse_depth_where_end_point_rays_meet_the_line_and_its_jacobian():
    """RGB-D line end points measure depth: the model's 1/z where a ray meets the line, and d/d(n, d)."""
    rng = np.random.default_rng(7)
    p1 = rng.normal(0, 1, (6, 3)) + [0, 0, 4]
    p2 = rng.normal(0, 1, (6, 3)) + [0, 0, 4]
    L = pl.from_points(p1, p2) * rng.uniform(0.5, 2.0, (6, 1))  # homogeneous: the scale must not matter
    X = p1[:, None, :] + np.array([0.1, 0.8])[None, :, None] * (p2 - p1)[:, None, :]  # points on the lines
    K = np.array([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]])
    uv = X @ K.T
    segs = (uv[..., :2] / uv[..., 2:]).reshape(6, 4)
    rays = pl.end_rays(segs, pl.line_projection_matrix(500.0, 510.0, 320.0, 240.0))
    np.testing.assert_allclose(rays, X / X[..., 2:], atol=1e-12)
    rho, d_n, d_d = pl.inverse_depth(L[:, :3], L[:, 3:], rays, jac=True)
    np.testing.assert_allclose(rho, 1.0 / X[..., 2], rtol=1e-10)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num_n = (pl.inverse_depth(L[:, :3] + e, L[:, 3:], rays)[0] - pl.inverse_depth(L[:, :3] - e, L[:, 3:], rays)[0]) / (2 * h)
        num_d = (pl.inverse_depth(L[:, :3], L[:, 3:] + e, rays)[0] - pl.inverse_depth(L[:, :3], L[:, 3:] - e, rays)[0]) / (2 * h)
        np.testing.assert_allclose(d_n[..., k], num_n, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(d_d[..., k], num_d, rtol=1e-6, atol=1e-8)
