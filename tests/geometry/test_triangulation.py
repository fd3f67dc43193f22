import time
import warnings

import numpy as np
import pytest

from vslam.geometry.se3 import inv_T, make_T, so3_exp
from vslam.geometry.triangulation import triangulate_points, triangulate_two_view

K = np.array([[520.0, 0.0, 320.0], [0.0, 510.0, 240.0], [0.0, 0.0, 1.0]])


def _project(T_world_c: np.ndarray, pts_world: np.ndarray) -> np.ndarray:
    """Pinhole projection (also of points behind the camera, which land mirrored)."""
    T_c_w = inv_T(T_world_c)
    p = pts_world @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    return p[:, :2] / p[:, 2:3] @ K[:2, :2].T + K[:2, 2]


def _two_cameras_and_points(n: int, seed: int = 0):
    """Two generic poses (neither is the identity) ~1 m apart and n points 3-10 m in front of both."""
    rng = np.random.default_rng(seed)
    T1 = make_T(so3_exp([0.1, -0.2, 0.05]), [0.5, -0.3, 1.0])
    T2 = T1 @ make_T(so3_exp([0.02, -0.1, 0.03]), [-0.9, 0.1, 0.2])
    z = rng.uniform(3.0, 10.0, n)
    xy = rng.uniform(-0.4, 0.4, (n, 2)) * z[:, None]
    pts = np.hstack([xy, z[:, None]]) @ T1[:3, :3].T + T1[:3, 3]
    return T1, T2, pts


def test_exact_data_gives_exact_points_in_world_frame():
    T1, T2, pts = _two_cameras_and_points(500)
    X, ok = triangulate_points(T1, T2, _project(T1, pts), _project(T2, pts), K)
    assert X.shape == (500, 3) and ok.shape == (500,) and ok.dtype == bool
    assert ok.all()
    rel = np.linalg.norm(X - pts, axis=1) / np.linalg.norm(pts, axis=1)
    assert rel.max() < 1e-9


def test_noisy_data_gives_small_error():
    T1, T2, pts = _two_cameras_and_points(1000, seed=1)
    rng = np.random.default_rng(2)
    uv1 = _project(T1, pts) + rng.normal(0.0, 0.5, (1000, 2))
    uv2 = _project(T2, pts) + rng.normal(0.0, 0.5, (1000, 2))
    X, ok = triangulate_points(T1, T2, uv1, uv2, K)
    assert ok.mean() > 0.95  # a few far points fall under 1 deg parallax, none should fail reprojection
    depth = np.linalg.norm(pts - T1[:3, 3], axis=1)
    rel = np.linalg.norm(X - pts, axis=1)[ok] / depth[ok]
    assert np.median(rel) < 0.01 and rel.max() < 0.1


def test_checks_flag_behind_low_parallax_and_bad_reprojection():
    T1 = np.eye(4)
    T2 = make_T(np.eye(3), [1.0, 0.0, 0.0])
    pts = np.array([
        [0.2, 0.1, 5.0],  # good
        [0.5, 0.0, 1.0e4],  # far away: parallax ~0.006 deg
        [0.3, -0.2, 6.0],  # good, but uv2 is moved off the epipolar line below
    ])
    uv1, uv2 = _project(T1, pts), _project(T2, pts)
    uv2[2, 1] += 8.0
    X, ok = triangulate_points(T1, T2, uv1, uv2, K, min_parallax_deg=1.0, max_reproj_px=2.0)
    assert ok.tolist() == [True, False, False]
    # each flag comes from its own check: relaxing that check alone accepts the point
    assert triangulate_points(T1, T2, uv1, uv2, K, min_parallax_deg=0.0)[1].tolist() == [True, True, False]
    assert triangulate_points(T1, T2, uv1, uv2, K, max_reproj_px=50.0)[1].tolist() == [True, False, True]
    np.testing.assert_allclose(X[:2], pts[:2], rtol=1e-9)


def test_point_behind_a_camera_is_rejected():
    # camera 2 stands 5 m behind camera 1, both looking along +z; the point is between them
    T1 = np.eye(4)
    T2 = make_T(so3_exp([0.0, 0.05, 0.0]), [0.5, 0.0, -5.0])
    pts = np.array([[0.3, 0.2, -2.0], [0.3, 0.2, 4.0]])
    tri = triangulate_two_view(T1, T2, _project(T1, pts), _project(T2, pts), K)
    np.testing.assert_allclose(tri.pts_world, pts, rtol=1e-9)
    assert tri.depth1[0] < 0 < tri.depth2[0]
    assert tri.ok(1.0, 2.0).tolist() == [False, True]


def test_identical_poses_flag_everything_without_exception_or_warning():
    T = make_T(so3_exp([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [640, 480], (50, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        X, ok = triangulate_points(T, T, uv, uv, K)  # same pixels: parallel rays
        X2, ok2 = triangulate_points(T, T, uv, uv[::-1], K)  # different pixels: rays meet at the centre
    assert X.shape == (50, 3) and not ok.any() and np.isnan(X).all()
    assert X2.shape == (50, 3) and not ok2.any()


def test_empty_input():
    X, ok = triangulate_points(np.eye(4), make_T(np.eye(3), [1, 0, 0]), np.zeros((0, 2)), np.zeros((0, 2)), K)
    assert X.shape == (0, 3) and ok.shape == (0,) and ok.dtype == bool


def test_shape_mismatch_raises():
    with pytest.raises(ValueError):
        triangulate_points(np.eye(4), np.eye(4), np.zeros((3, 2)), np.zeros((4, 2)), K)
    with pytest.raises(ValueError):
        triangulate_points(np.eye(4), np.eye(4), np.zeros((3, 3)), np.zeros((3, 3)), K)


def test_2000_pairs_are_vectorised_fast():
    T1, T2, pts = _two_cameras_and_points(2000)
    uv1, uv2 = _project(T1, pts), _project(T2, pts)
    triangulate_points(T1, T2, uv1, uv2, K)
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        triangulate_points(T1, T2, uv1, uv2, K)
        best = min(best, time.perf_counter() - t0)
    assert best < 0.015  # measured ~0.7 ms; a Python loop over points takes tens of ms
