"""Line reprojection factor (GTSAM CustomFactor) and line landmarks in local BA."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from tests.backend import _synth as S
from vslam.backend import line_factor as lf
from vslam.backend.ba import BackendConfig, local_bundle_adjustment
from vslam.backend.line_ba import LineProblem
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import inv_T, make_T, so3_exp

CAM = S.CAM
K = np.array([[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1.0]])
K_L = pl.line_projection_matrix(CAM.fx, CAM.fy, CAM.cx, CAM.cy)


def _seg(T_world_cam: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    Tcw = inv_T(T_world_cam)
    pa, pb = K @ (Tcw[:3, :3] @ a + Tcw[:3, 3]), K @ (Tcw[:3, :3] @ b + Tcw[:3, 3])
    return np.r_[pa[:2] / pa[2], pb[:2] / pb[2]]


def _retracted(v: gtsam.Values, key: int, dim: int, d: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(v)
    out.erase(key)
    if dim == 3:
        out.insert(key, v.atRot3(key).retract(d))
    elif dim == 1:
        out.insert(key, v.atRot2(key).retract(d))
    else:
        out.insert(key, v.atPose3(key).retract(d))
    return out


def _factor_and_values(huber_k, noise_px=3.0):
    rng = np.random.default_rng(0)
    a, b = np.array([0.3, -0.2, 4.0]), np.array([-0.5, 0.6, 5.5])
    poses = [make_T(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.3, 3)) for _ in range(3)]
    # noisy segments (several px, beyond the Huber threshold) so the robust branch is exercised
    segs = np.array([_seg(T, a, b) for T in poses]) + rng.normal(0, noise_px, (3, 4))
    f = lf.line_factor(7, [0, 1, 2], segs, K_L, 1.0, huber_k)
    v = gtsam.Values()
    lf.insert_line(v, 7, pl.from_points(a, b))
    for i, T in enumerate(poses):
        v.insert(X(i), gtsam.Pose3(T))
    return f, v


def test_analytic_jacobian_equals_numeric():
    f, v = _factor_and_values(None)
    A, b = f.linearize(v).jacobian()
    cols, h = [], 1e-6
    for key, dim in zip(f.keys(), [3, 1, 6, 6, 6]):
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = h
            cols.append((f.unwhitenedError(_retracted(v, key, dim, d)) - f.unwhitenedError(_retracted(v, key, dim, -d))) / (2 * h))
    Jn = np.array(cols).T
    assert np.abs(A).max() > 10.0  # a real Jacobian, pixels per radian/metre
    assert np.abs(A - Jn).max() <= 1e-6 * np.abs(A).max()
    np.testing.assert_allclose(-b, f.unwhitenedError(v), atol=1e-12)
    # the pose blocks are zero outside their own observation's rows
    assert np.all(A[2:, 4:10] == 0.0) and np.all(A[:2, 10:16] == 0.0)


def test_huber_is_irls_per_observation_like_gtsam_robust():
    f0, v = _factor_and_values(None)
    fk, _ = _factor_and_values(1.345)
    A0, b0 = f0.linearize(v).jacobian()
    Ak, bk = fk.linearize(v).jacobian()
    e = b0.reshape(-1, 2)
    a = np.linalg.norm(e, axis=1)
    assert (a > 1.345).sum() >= 2  # the robust branch is exercised
    sw = np.repeat(np.sqrt(np.minimum(1.0, 1.345 / a)), 2)
    np.testing.assert_allclose(Ak, sw[:, None] * A0, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(bk, sw * b0, rtol=1e-12)
    rho = np.where(a <= 1.345, 0.5 * a * a, 1.345 * a - 0.5 * 1.345**2)
    assert fk.error(v) == pytest.approx(rho.sum(), rel=1e-12)


def test_error_is_end_point_distance_and_huber_cost():
    a, b = np.array([0.0, 0.0, 5.0]), np.array([1.0, 0.0, 5.0])  # horizontal line through the principal point
    seg = _seg(np.eye(4), a, b) + np.array([0.0, 3.0, 0.0, -4.0])  # end points 3 px below, 4 px above
    v = gtsam.Values()
    lf.insert_line(v, 0, pl.from_points(a, b))
    v.insert(X(0), gtsam.Pose3())
    e = lf.line_factor(0, [0], seg[None], K_L, 2.0, None).unwhitenedError(v)
    np.testing.assert_allclose(np.abs(e), [1.5, 2.0], atol=1e-9)  # pixels / sigma
    k = 1.0
    err = lf.line_factor(0, [0], seg[None], K_L, 2.0, k).error(v)
    assert err == pytest.approx(k * 2.5 - 0.5 * k * k, rel=1e-9)  # Huber rho of the norm 2.5


def _numeric_pose_gradient(f, v: gtsam.Values, n_poses: int, h: float = 1e-6) -> np.ndarray:
    """Central differences of f.error over every pose X(0..n-1), 6 tangent directions each -> (6n,)."""
    num = []
    for k in range(n_poses):
        for i in range(6):
            d = np.zeros(6)
            d[i] = h
            num.append((f.error(_retracted(v, X(k), 6, d)) - f.error(_retracted(v, X(k), 6, -d))) / (2 * h))
    return np.array(num)


def _line_scene(rng, n_kf=6, n_lines=40, n_pts=12):
    poses = S.camera_path(rng, n_kf)
    lines, segs_kf, segs_ln, segs = {}, [], [], []
    j = 0
    while len(lines) < n_lines:
        a = np.array([rng.uniform(-2, 2.6), rng.uniform(-1.5, 1.5), rng.uniform(4, 9)])
        b = a + rng.normal(0, 1.0, 3)
        ok = all(S.visible(T, np.stack([a, b])).all() for T in poses)
        if not ok:
            continue
        lines[j] = pl.normalize(pl.from_points(a, b))
        for k, T in enumerate(poses):
            segs_kf.append(k), segs_ln.append(j), segs.append(_seg(T, a, b))
        j += 1
    pts = np.column_stack([rng.uniform(-2.0, 2.6, n_pts), rng.uniform(-1.5, 1.5, n_pts), rng.uniform(4.0, 9.0, n_pts)])
    pairs = [(k, i) for k in range(n_kf) for i in np.flatnonzero(S.visible(poses[k], pts)).tolist()]
    prob = S._problem(rng, poses, pts, pairs, stereo_frac=0.0)  # monocular points: weak alone
    lp = LineProblem(lines, np.array(segs_kf), np.array(segs_ln), np.array(segs))
    return poses, prob, lp


def _perturbed(rng, prob, lp, seg_noise_px: float, pt_noise_px: float):
    noisy = S.perturb(rng, prob, trans_m=0.03, rot_deg=1.5, pt_m=0.05)
    noisy.obs_uv = noisy.obs_uv + rng.normal(0, pt_noise_px, noisy.obs_uv.shape)
    lines0 = {}
    for j, L in lp.lines.items():  # lines moved by ~0.02 rad in each of their 4 DoF
        U, w = pl.to_orthonormal(L)
        lines0[j] = pl.from_orthonormal(*pl.orthonormal_retract(U, w, rng.normal(0, 0.02, 4)))
    noisy.lines = dataclasses.replace(lp, lines=lines0, obs_seg=lp.obs_seg + rng.normal(0, seg_noise_px, lp.obs_seg.shape))
    return noisy


@pytest.mark.parametrize("mode", ["window", "landmark"])
def test_ba_with_lines_recovers_perturbed_poses(mode):
    rng = np.random.default_rng(3)
    poses, prob, lp = _line_scene(rng, n_lines=25)
    prob.fixed = {0, 1}
    lp = dataclasses.replace(lp, mode=mode)
    cfg = BackendConfig(max_iterations=15, refine_iterations=3)
    # noiseless: poses 3 cm / 1.5 deg off, points 5 cm, lines 0.02 rad -> back to the truth
    res = local_bundle_adjustment(_perturbed(rng, prob, lp, 0.0, 0.0), CAM, cfg)
    for k in range(2, len(poses)):
        t_err, r_err = S.pose_error(res.poses[k], poses[k])
        assert t_err < 2e-4 and r_err < 2e-3, (k, t_err, r_err)
    assert res.line_inliers is not None and res.line_inliers.all()
    for j, L in res.lines.items():  # lines back to the truth (same line up to sign)
        assert abs(L[3:] @ lp.lines[j][3:]) > 1 - 1e-6
        assert np.linalg.norm(pl.closest_point(L) - pl.closest_point(lp.lines[j])) < 1e-3
    # 0.3 px noise on both: 12 monocular points alone drift (the scale is weak); lines pin the poses
    noisy = _perturbed(rng, prob, lp, 0.3, 0.3)
    worst_lines = max(S.pose_error(local_bundle_adjustment(noisy, CAM, cfg).poses[k], poses[k])[0] for k in range(2, 6))
    noisy.lines = None
    worst_pts = max(S.pose_error(local_bundle_adjustment(noisy, CAM, cfg).poses[k], poses[k])[0] for k in range(2, 6))
    assert worst_lines < 0.5 * worst_pts, (worst_lines, worst_pts)  # measured 0.037 vs 0.099 m (window)


def test_ba_flags_line_outlier_and_keeps_lines_off_by_default():
    rng = np.random.default_rng(4)
    poses, prob, lp = _line_scene(rng, n_lines=20)
    prob.fixed = {0, 1}
    seg = lp.obs_seg.copy()
    seg[5] += np.array([0.0, 25.0, 0.0, 25.0])  # one observation 25 px off
    prob.lines = dataclasses.replace(lp, obs_seg=seg)
    res = local_bundle_adjustment(prob, CAM, BackendConfig())
    assert not res.line_inliers[5] and res.line_inliers.sum() == len(seg) - 1
    prob.lines = None
    res = local_bundle_adjustment(prob, CAM, BackendConfig())
    assert res.line_inliers is None and res.lines == {}


def _noisy_window(seed: int, noise_px: float):
    """-> (rng, true poses, LineWindow of 8 lines over them, segments with ``noise_px`` of noise, Huber 1.345)."""
    from vslam.backend.line_window import LineWindow

    rng = np.random.default_rng(seed)
    poses, _, lp = _line_scene(rng, n_lines=8)
    segs = lp.obs_seg + rng.normal(0, noise_px, lp.obs_seg.shape)
    win = LineWindow(np.array([lp.lines[j] for j in sorted(lp.lines)]), lp.obs_line, lp.obs_kf, segs,
                     [X(k) for k in range(len(poses))], K_L, 1.0, 1.345)
    return rng, poses, win


def test_window_factor_gradient_and_error_match_the_line_cost():
    """The structureless window factor: at converged lines its error is the lines' Huber cost and J^T r is
    the gradient of that error over the poses (null-space projection keeps the Schur complement exact)."""
    rng, poses, win = _noisy_window(5, 0.5)
    f = win.factor()
    v = gtsam.Values()
    for k, T in enumerate(poses):
        v.insert(X(k), gtsam.Pose3(S.perturb_pose(rng, T, 0.005, 0.2)))
    for _ in range(20):  # converge the lines (each linearisation re-anchors them; IRLS converges linearly)
        f.linearize(v)
    A, b = f.linearize(v).jacobian()
    grad = A.T @ (-b)  # J^T r (b = -r)
    # error = Huber cost of all observations at the re-solved lines
    e = win.whitened_sq_errors(np.array([v.atPose3(X(k)).matrix() for k in range(len(poses))]))
    a = np.sqrt(e)
    assert f.error(v) == pytest.approx(np.sum(np.where(a <= 1.345, 0.5 * e, 1.345 * a - 0.5 * 1.345**2)), rel=1e-6)
    num = _numeric_pose_gradient(f, v, len(poses))
    assert np.abs(grad).max() > 1.0
    assert np.abs(grad - num).max() <= 1e-3 * np.abs(grad).max(), np.abs(grad - num).max()


def test_window_factor_on_body_poses_is_the_camera_factor_carried_through_T_body_cam():
    """Visual-inertial BA keys body poses: the same lines seen by cameras T_world_body T_body_cam give the
    same error, and the body Jacobians are the camera ones times Ad(T_cam_body) (checked numerically)."""
    from vslam.backend.line_window import LineWindow
    from vslam.geometry.se3 import inv_T, make_T, so3_exp

    rng = np.random.default_rng(6)
    poses, _, lp = _line_scene(rng, n_lines=8)
    segs = lp.obs_seg + rng.normal(0, 0.5, lp.obs_seg.shape)
    T_bc = make_T(so3_exp(np.array([0.1, -0.2, 0.05])), np.array([0.05, -0.02, 0.1]))
    args = (np.array([lp.lines[j] for j in sorted(lp.lines)]), lp.obs_line, lp.obs_kf, segs, [X(k) for k in range(len(poses))],
            K_L, 1.0, 1.345)
    f_cam, f_body = LineWindow(*args).factor(), LineWindow(*args, T_body_cam=T_bc).factor()
    vc, vb = gtsam.Values(), gtsam.Values()
    for k, T in enumerate(poses):
        Tp = S.perturb_pose(rng, T, 0.005, 0.2)
        vc.insert(X(k), gtsam.Pose3(Tp))
        vb.insert(X(k), gtsam.Pose3(Tp @ inv_T(T_bc)))
    assert f_body.error(vb) == pytest.approx(f_cam.error(vc), rel=1e-9)
    for _ in range(60):  # converge the lines (IRLS converges linearly; measured 1e-8 relative after 60)
        f_body.linearize(vb)
    A, b = f_body.linearize(vb).jacobian()
    grad = A.T @ (-b)
    num = _numeric_pose_gradient(f_body, vb, len(poses))
    assert np.abs(grad).max() > 1.0
    assert np.abs(grad - num).max() <= 1e-3 * np.abs(grad).max(), np.abs(grad - num).max()


def test_window_factor_linearises_an_accepted_point_without_solving_its_lines_again(monkeypatch):
    """LM linearises where error() was just evaluated: the lines solved there are reused (one back-substitution,
    not two), and the linear factor is the one a window that never saw that error() call gives, bit for bit."""
    from vslam.backend.line_window import LineWindow

    rng = np.random.default_rng(7)
    poses, _, lp = _line_scene(rng, n_lines=8)
    segs = lp.obs_seg + rng.normal(0, 0.5, lp.obs_seg.shape)
    args = (np.array([lp.lines[j] for j in sorted(lp.lines)]), lp.obs_line, lp.obs_kf, segs,
            [X(k) for k in range(len(poses))], K_L, 1.0, 1.345)
    v0, v1 = gtsam.Values(), gtsam.Values()
    for k, T in enumerate(poses):
        v0.insert(X(k), gtsam.Pose3(S.perturb_pose(rng, T, 0.005, 0.2)))
        v1.insert(X(k), gtsam.Pose3(S.perturb_pose(rng, T, 0.005, 0.2)))
    wa, wb = LineWindow(*args), LineWindow(*args)
    fa, fb = wa.factor(), wb.factor()
    for f in (fa, fb):  # prime and anchor both at v0
        f.error(v0)
        f.linearize(v0)
    solves = []
    real = LineWindow._predict
    monkeypatch.setattr(LineWindow, "_predict", lambda self, *a, **k: solves.append(self) or real(self, *a, **k))
    fa.error(v1)  # LM's trial point ...
    Aa, ba_ = fa.linearize(v1).jacobian()  # ... accepted and linearised: no second solve
    assert solves == [wa]
    Ab, bb = fb.linearize(v1).jacobian()  # the same point without the error() call first
    assert np.array_equal(Aa, Ab) and np.array_equal(ba_, bb)
    fa.error(v0)  # the anchor moved at the linearisation: a new point is solved again
    assert solves == [wa, wb, wa]


def test_window_factor_back_substitutes_its_lines_for_a_pose_step():
    """Between linearisations the lines follow the poses by back-substitution (the line part of the joint
    Gauss-Newton step): for a small pose step they reach nearly the cost of lines re-converged at the new poses,
    far below the cost of the anchor lines there."""
    rng, poses, win = _noisy_window(8, 0.3)
    f = win.factor()
    v0, v1 = gtsam.Values(), gtsam.Values()
    for k, T in enumerate(poses):
        T0 = S.perturb_pose(rng, T, 0.003, 0.1)
        v0.insert(X(k), gtsam.Pose3(T0))
        v1.insert(X(k), gtsam.Pose3(S.perturb_pose(rng, T0, 0.002, 0.05)))
    for _ in range(20):  # lines converged at v0 and the factor linearised there
        f.linearize(v0)
    T1 = win.camera_poses(v1)
    _, _, predicted = win.lines_at(T1)
    _, _, anchor = win.refine_lines(T1, 0)
    _, _, converged = win.refine_lines(T1, 30)
    gap = anchor.sum() - converged.sum()
    assert gap > 1.0, gap  # the step moves the lines' optimum measurably
    assert predicted.sum() - converged.sum() <= 0.05 * gap, (predicted.sum(), converged.sum(), anchor.sum())  # 2.3 % (one LM step: 0.5 %)


def _end_inverse_depths(lp: LineProblem, poses, segs) -> np.ndarray:
    """(M,2) true inverse depths of each observation's end points, read along its (noisy) end-point rays."""
    from vslam.geometry.se3 import inv_T

    L = np.array([lp.lines[j] for j in lp.obs_line.tolist()])
    Lc = np.array([pl.transform(L[i], inv_T(poses[k])) for i, k in enumerate(lp.obs_kf.tolist())])
    return pl.inverse_depth(Lc[:, :3], Lc[:, 3:], pl.end_rays(segs, K_L))[0]


def test_window_factor_with_end_point_depths_matches_its_cost_and_numeric_gradient():
    """RGB-D line observations carry two inverse-depth rows: the window's error is the Huber cost of all four
    rows, its gradient matches central differences, and a line seen twice now has pose information."""
    from vslam.backend.line_window import LineWindow

    rng = np.random.default_rng(8)
    poses, _, lp = _line_scene(rng, n_lines=8)
    segs = lp.obs_seg + rng.normal(0, 0.5, lp.obs_seg.shape)
    rho = _end_inverse_depths(lp, poses, segs) * rng.uniform(0.99, 1.01, (len(segs), 2))
    rho[::7, 1] = np.nan  # some end points without depth
    w = CAM.fx * 0.08 / 0.05
    lines = np.array([lp.lines[j] for j in sorted(lp.lines)])
    win = LineWindow(lines, lp.obs_line, lp.obs_kf, segs, [X(k) for k in range(len(poses))], K_L, 1.0, 1.345,
                     rho=rho, depth_weight=w)
    assert win.k == 4 and win.dim == 8 * (4 * len(poses) - 4)
    two = LineWindow(lines[:1], np.zeros(2, np.int64), np.arange(2), segs[:2], [X(0), X(1)], K_L, 1.0, None)
    two_d = LineWindow(lines[:1], np.zeros(2, np.int64), np.arange(2), segs[:2], [X(0), X(1)], K_L, 1.0, None,
                       rho=rho[:2], depth_weight=w)
    assert two.factor() is None and two_d.dim == 4
    f = win.factor()
    v = gtsam.Values()
    for k, T in enumerate(poses):
        v.insert(X(k), gtsam.Pose3(S.perturb_pose(rng, T, 0.005, 0.2)))
    for _ in range(12):
        f.linearize(v)
    A, b = f.linearize(v).jacobian()
    grad = A.T @ (-b)
    e = win.whitened_sq_errors(np.array([v.atPose3(X(k)).matrix() for k in range(len(poses))]))
    a = np.sqrt(e)
    assert f.error(v) == pytest.approx(np.sum(np.where(a <= 1.345, 0.5 * e, 1.345 * a - 0.5 * 1.345**2)), rel=1e-6)
    no_depth = LineWindow(lines, lp.obs_line, lp.obs_kf, segs, [X(k) for k in range(len(poses))], K_L, 1.0, 1.345)
    no_depth.U, no_depth.w = win.U, win.w
    assert e.sum() > 1.5 * no_depth.whitened_sq_errors(np.array([v.atPose3(X(k)).matrix() for k in range(len(poses))])).sum()
    num = _numeric_pose_gradient(f, v, len(poses))
    assert np.abs(grad - num).max() <= 1e-3 * np.abs(grad).max(), np.abs(grad - num).max()


def test_ba_with_end_point_depths_flags_a_wrong_depth_and_line_chi2_counts_its_rows():
    rng = np.random.default_rng(9)
    poses, prob, lp = _line_scene(rng, n_lines=20)
    prob.fixed = {0, 1}
    rho = _end_inverse_depths(lp, poses, lp.obs_seg)
    rho[5] *= 1.2  # one observation's depth 20 % off
    rho[6, 0] = np.nan
    prob.lines = dataclasses.replace(lp, obs_rho=rho, depth_weight=CAM.fx * 0.08 / 0.05)
    res = local_bundle_adjustment(prob, CAM, BackendConfig())
    assert not res.line_inliers[5] and res.line_inliers.sum() == len(rho) - 1
    # 95 % of chi2(2 + end points with a depth)
    at9, at7 = prob.lines.inliers(np.full(len(rho), 9.0)), prob.lines.inliers(np.full(len(rho), 7.0))
    assert not at9[6] and at9.sum() == len(rho) - 1 and at7.all()
    assert not dataclasses.replace(prob.lines, obs_rho=None).inliers(np.full(len(rho), 7.0)).any()
    with pytest.raises(ValueError, match="window"):
        from vslam.backend.line_ba import line_terms

        line_terms(dataclasses.replace(prob.lines, mode="landmark"), set(range(len(poses))), K_L, 1.345)


def test_window_factor_rows_give_the_null_space_projected_system():
    """The window hands GTSAM 6K rows J, r whose normal equations J^T J, J^T r are those of the null-space
    projected rows Q^T J_x, Q^T r of every line (the per-line Schur complement), with and without depths;
    lines without pose information (seen twice, no depths) add nothing; held poses leave the factor."""
    from vslam.backend.line_window import LineWindow

    rng = np.random.default_rng(11)
    poses, _, lp = _line_scene(rng, n_lines=10)
    segs = lp.obs_seg + rng.normal(0, 0.5, lp.obs_seg.shape)
    rho = _end_inverse_depths(lp, poses, segs) * rng.uniform(0.99, 1.01, (len(segs), 2))
    rho[::5, 0] = np.nan
    lines = np.array([lp.lines[j] for j in sorted(lp.lines)])
    keep = ~((lp.obs_line == 3) & (lp.obs_kf >= 2))  # line 3 seen twice only
    Twc = np.array([S.perturb_pose(rng, T, 0.005, 0.2) for T in poses])
    for kw in ({}, {"rho": rho[keep], "depth_weight": CAM.fx * 0.08 / 0.05}):
        win = LineWindow(lines, lp.obs_line[keep], lp.obs_kf[keep], segs[keep], [X(k) for k in range(len(poses))],
                         K_L, 1.0, 1.345, **kw)
        r, Jl, Jx = win._residuals(win._geom(Twc), win.U, win.w, True)
        H = np.zeros((6 * len(poses),) * 2)
        g = np.zeros(6 * len(poses))
        for j in range(win.n_lines):
            o = np.flatnonzero(win.ol == j)
            if win.count[j] < win.min_views:
                continue
            A = Jl[o].reshape(-1, 4)
            Q = np.linalg.qr(A, mode="complete")[0][:, 4:]
            Jfull = np.zeros((len(o), win.k, len(poses), 6))
            Jfull[np.arange(len(o)), :, win.op[o]] = Jx[o]
            Jp, rp = Q.T @ Jfull.reshape(len(o) * win.k, -1), Q.T @ r[o].reshape(-1)
            H += Jp.T @ Jp
            g += Jp.T @ rp
        rr, J = win._reduced(Twc, win.U, win.w)
        assert J.shape == (6 * len(poses), 6 * len(poses)) and np.abs(H).max() > 1.0
        np.testing.assert_allclose(J.T @ J, H, atol=1e-9 * np.abs(H).max())
        np.testing.assert_allclose(J.T @ rr, g, atol=1e-9 * np.abs(g).max())
        # poses the graph holds (fixed keyframes) leave the factor: the free poses' block of the same system
        held = LineWindow(lines, lp.obs_line[keep], lp.obs_kf[keep], segs[keep], [X(k) for k in range(len(poses))],
                          K_L, 1.0, 1.345, held={X(0), X(2)}, **kw)
        free = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in range(len(poses)) if k not in (0, 2)])
        rh, Jh = held._reduced(Twc, held.U, held.w)
        assert Jh.shape == (len(free), len(free)) and held.factor().keys() == [X(k) for k in (1, 3, 4, 5)]
        np.testing.assert_allclose(Jh.T @ Jh, H[np.ix_(free, free)], atol=1e-9 * np.abs(H).max())
        np.testing.assert_allclose(Jh.T @ rh, g[free], atol=1e-9 * np.abs(g).max())
