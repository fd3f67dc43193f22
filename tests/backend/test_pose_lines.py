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


def _scene(rng, T, n_lines, n_pts):
    a = np.column_stack([rng.uniform(-2, 2, n_lines), rng.uniform(-1.5, 1.5, n_lines), rng.uniform(3, 7, n_lines)])
    b = a + rng.normal(0, 1.0, (n_lines, 3))
    b[:, 2] = np.clip(b[:, 2], 2.5, 8)
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
