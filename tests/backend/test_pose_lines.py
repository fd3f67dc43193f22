"""Pose-only refinement with points and lines."""

from __future__ import annotations

import numpy as np

from tests.backend import _synth as S
from vslam.backend.ba import BackendConfig, optimize_pose
from vslam.backend.pose_lines import refine_pose_points_lines
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import inv_T

CAM = S.CAM
K = np.array([[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1.0]])
K_L = pl.line_projection_matrix(CAM.fx, CAM.fy, CAM.cx, CAM.cy)


def _scene(rng, T, n_lines, n_pts, scale=1.0):
    """Lines (and points) 3-7 m in front of camera T (times ``scale``): world Plücker lines, their segments,
    world points and their pixels."""
    a = np.column_stack([rng.uniform(-2, 2, n_lines), rng.uniform(-1.5, 1.5, n_lines), rng.uniform(3, 7, n_lines)])
    b = a + rng.normal(0, 1.0, (n_lines, 3))
    b[:, 2] = np.clip(b[:, 2], 2.5, 8)
    a, b = scale * a, scale * b
    Aw, Bw = a @ T[:3, :3].T + T[:3, 3], b @ T[:3, :3].T + T[:3, 3]
    segs = np.hstack([(a @ K.T)[:, :2] / a[:, 2:], (b @ K.T)[:, :2] / b[:, 2:]])
    L = pl.normalize(pl.from_points(Aw, Bw))
    P = np.column_stack([rng.uniform(-2, 2, n_pts), rng.uniform(-1.5, 1.5, n_pts), rng.uniform(3, 7, n_pts)])
    uv = (P @ K.T)[:, :2] / P[:, 2:]
    return L, segs, P @ T[:3, :3].T + T[:3, 3], uv


def test_lines_alone_fix_the_pose_and_outliers_are_flagged():
    rng = np.random.default_rng(0)
    T = S.camera_path(rng, 2)[1]
    L, segs, Pw, uv = _scene(rng, T, 30, 0)
    segs = segs + rng.normal(0, 0.3, segs.shape)
    segs[3] += np.array([0, 20.0, 0, 20.0])  # one outlier, 20 px off
    T0 = S.perturb_pose(rng, T, 0.05, 2.0)
    T1, pin, lin = refine_pose_points_lines(T0, Pw, uv, np.full(0, np.nan), L, segs, K_L, CAM, BackendConfig())
    t_err, r_err = S.pose_error(T1, T)
    assert t_err < 0.01 and r_err < 0.1, (t_err, r_err)
    assert not lin[3] and lin.sum() >= 27


def test_lines_help_when_points_are_few():
    rng = np.random.default_rng(1)
    errs_p, errs_pl = [], []
    for _ in range(10):
        T = S.camera_path(rng, 2)[1]
        L, segs, Pw, uv = _scene(rng, T, 25, 6)
        uv = uv + rng.normal(0, 1.0, uv.shape)
        segs = segs + rng.normal(0, 1.0, segs.shape)
        T0 = S.perturb_pose(rng, T, 0.03, 1.0)
        ur = np.full(len(uv), np.nan)
        errs_p.append(S.pose_error(optimize_pose(T0, Pw, uv, ur, CAM, BackendConfig())[0], T)[0])
        errs_pl.append(S.pose_error(refine_pose_points_lines(T0, Pw, uv, ur, L, segs, K_L, CAM, BackendConfig())[0], T)[0])
    assert np.median(errs_pl) < 0.5 * np.median(errs_p), (np.median(errs_pl), np.median(errs_p))


def test_right_camera_rows_jacobian_matches_numeric():
    """The virtual right-camera rows (a line's depth, RGB-D) and their Jacobian through Ad(T_r_c)."""
    from vslam.backend.pose_lines import _Right
    from vslam.geometry.se3 import so3_exp

    rng = np.random.default_rng(4)
    T = S.camera_path(rng, 2)[1]
    L, segs, _, _ = _scene(rng, T, 12, 0)
    T_cw = inv_T(S.perturb_pose(rng, T, 0.02, 1.0))
    right = _Right(segs + rng.normal(0, 2.0, segs.shape), np.ones(len(segs), bool), np.array([-0.08, 0, 0]), 0.5)
    e0, J = right.block(T_cw, L, segs, K_L, True)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        Tp = T_cw.copy()  # T_cam_world <- [Exp(w) | v] T_cam_world
        Tp[:3, :3] = so3_exp(d[:3]) @ T_cw[:3, :3]
        Tp[:3, 3] = so3_exp(d[:3]) @ T_cw[:3, 3] + d[3:]
        num = (right.block(Tp, L, segs, K_L, False)[0] - e0) / h
        np.testing.assert_allclose(J[:, :, k], num, atol=1e-4 * max(1.0, np.abs(num).max()))


def test_line_depth_rows_sharpen_a_pose_from_few_lines():
    """12 lines 1.5-3.5 m away (a room), 1 px end-point noise: the lines' depth (virtual right segments from
    the true end-point depths, 0.1 px disparity noise, the points' RGB-D default) tightens the pose."""
    rng = np.random.default_rng(5)
    errs_2d, errs_3d = [], []
    none = (np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0))
    for _ in range(20):
        T = S.camera_path(rng, 2)[1]
        L, segs, _, _ = _scene(rng, T, 12, 0, scale=0.5)
        Tcw = inv_T(T)
        A, B = pl.clip_to_segment(L, segs, T, K)
        za, zb = (A @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2], (B @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2]
        noise = rng.normal(0, 1.0, segs.shape)
        noisy = segs + noise
        noisy_r = noisy.copy()  # the same image end points, shifted by their (slightly noisy) disparity
        noisy_r[:, 0] -= CAM.fx * CAM.baseline / za + rng.normal(0, 0.1, len(za))
        noisy_r[:, 2] -= CAM.fx * CAM.baseline / zb + rng.normal(0, 0.1, len(zb))
        T0 = S.perturb_pose(rng, T, 0.05, 1.0)
        errs_2d.append(S.pose_error(refine_pose_points_lines(T0, *none, L, noisy, K_L, CAM, BackendConfig())[0], T)[0])
        T3 = refine_pose_points_lines(T0, *none, L, noisy, K_L, CAM, BackendConfig(), segs_r=noisy_r, right_sigma=0.1)[0]
        errs_3d.append(S.pose_error(T3, T)[0])
    assert np.median(errs_3d) < 0.6 * np.median(errs_2d), (np.median(errs_3d), np.median(errs_2d))  # 0.47x
