"""Local BA and pose-only refinement on synthetic problems with exact answers."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from tests.backend import _synth as S
from vslam.backend import pose_only
from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera, local_bundle_adjustment, optimize_pose
from vslam.backend.factors import FactorBuilder, L, X, pose3
from vslam.backend.projection import backproject_cam, measurement_matrix, project_stereo, whitened_sq_errors
from vslam.geometry.se3 import inv_T, make_T, so3_exp

_local_ba = local_bundle_adjustment


@pytest.fixture(autouse=True, params=["gtsam", "numpy"])
def solver(request, monkeypatch):
    """Every local BA test runs with both solvers: the GTSAM graph (the default) and the opt-in numpy Schur solver."""
    def run(problem, camera, cfg=BackendConfig()):
        return _local_ba(problem, camera, dataclasses.replace(cfg, solver=request.param))
    monkeypatch.setitem(globals(), "local_bundle_adjustment", run)
    return request.param


def _max_errors(result, poses, pts, skip_pts=()):
    t = max((S.pose_error(result.poses[k], poses[k])[0] for k in result.poses), default=0.0)
    r = max((S.pose_error(result.poses[k], poses[k])[1] for k in result.poses), default=0.0)
    p = max(np.linalg.norm(result.points[j] - pts[j]) for j in result.points if j not in skip_pts)
    return t, r, p


# --- conventions -------------------------------------------------------------------------------------


def test_projection_matches_gtsam_stereo_camera():
    rng = np.random.default_rng(0)
    T_world_cam = make_T(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 1.0, 3))
    pts_cam = np.column_stack([rng.uniform(-2, 2, 20), rng.uniform(-1, 1, 20), rng.uniform(1, 10, 20)])
    pts_world = pts_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    uv, ur, z = project_stereo(T_world_cam, pts_world, S.CAM)
    K = gtsam.Cal3_S2Stereo(S.CAM.fx, S.CAM.fy, 0.0, S.CAM.cx, S.CAM.cy, S.CAM.baseline)
    cam = gtsam.StereoCamera(gtsam.Pose3(T_world_cam), K)
    mono = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(T_world_cam), gtsam.Cal3_S2(S.CAM.fx, S.CAM.fy, 0.0, S.CAM.cx, S.CAM.cy))
    for i, p in enumerate(pts_world):
        sp = cam.project(p)
        np.testing.assert_allclose([sp.uL(), sp.v(), sp.uR()], [uv[i, 0], uv[i, 1], ur[i]], atol=1e-9)
        np.testing.assert_allclose(mono.project(p), uv[i], atol=1e-9)
    np.testing.assert_allclose(z, pts_cam[:, 2], atol=1e-12)
    meas = np.column_stack([uv, ur])  # and back: the inverse that places single-view points after local BA
    back = backproject_cam(meas, S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy, S.CAM.baseline)
    np.testing.assert_allclose(back, pts_cam, atol=1e-9)


def test_gtsam_factors_take_T_world_cam_and_match_numpy_residuals():
    rng = np.random.default_rng(1)
    T = S.camera_path(rng, 2)[1]
    p = np.array([[0.3, -0.2, 5.0]]) @ T[:3, :3].T + T[:3, 3]
    uv, ur, _ = project_stereo(T, p, S.CAM)
    meas, _ = measurement_matrix(uv + [[1.5, -2.0]], ur + 0.7)
    values = gtsam.Values()
    values.insert(X(3), pose3(T))
    values.insert(L(7), p[0])
    b = FactorBuilder(S.CAM, 1.345)
    f_st, f_mo = b.factors(np.array([3, 3]), np.array([7, 7]), np.vstack([meas, meas]), np.array([True, False]), np.ones(2))
    # both factors: predicted - measured at Pose3(T_world_cam); the stereo one in (uL, uR, v) order
    np.testing.assert_allclose(f_st.unwhitenedError(values), [-1.5, -0.7, 2.0], atol=1e-9)
    np.testing.assert_allclose(f_mo.unwhitenedError(values), [-1.5, 2.0], atol=1e-9)


def test_disparity_sigma_model_matches_gtsam_and_weights_depth():
    """RGB-D model (StereoCamera.disparity_sigma): numpy chi2 = GTSAM's whitened error of the correlated
    (uL, uR, v) covariance, and a pure depth error costs (sigma / disparity_sigma)^2 more than under the
    ORB-SLAM2 model, a shift of the keypoint (uL and uR together) the same."""
    rgbd = StereoCamera(S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy, S.CAM.baseline, disparity_sigma=0.1)
    rng = np.random.default_rng(5)
    T = S.camera_path(rng, 2)[1]
    p = np.array([[0.3, -0.2, 3.0]]) @ T[:3, :3].T + T[:3, 3]
    uv, ur, _ = project_stereo(T, p, rgbd)
    pc = (inv_T(T)[:3, :3] @ p[0] + inv_T(T)[:3, 3])[None]
    values = gtsam.Values()
    values.insert(X(0), pose3(T))
    values.insert(L(0), p[0])
    for du, dr in [(0.0, 0.3), (0.5, 0.5), (1.2, -0.4)]:
        meas, st = measurement_matrix(uv + [[du, 0.0]], ur + dr)
        (f,) = FactorBuilder(rgbd, 1e9).factors(np.array([0]), np.array([0]), meas, st, np.ones(1))
        chi2, _ = whitened_sq_errors(pc, meas, st, 1.0, rgbd)
        np.testing.assert_allclose(chi2[0], 2.0 * f.error(values), rtol=1e-9)  # Huber k = 1e9: plain LS
        old, _ = whitened_sq_errors(pc, meas, st, 1.0, S.CAM)
        if du == dr:  # the keypoint moved, the depth did not: only the uL term
            np.testing.assert_allclose(chi2[0], du**2, rtol=1e-9)
        if du == 0.0:  # a depth error alone
            np.testing.assert_allclose(chi2[0], old[0] * 100.0, rtol=1e-9)


@pytest.mark.parametrize("disparity_sigma", [0.0, 0.1])
def test_pose_only_gradient_matches_numeric(disparity_sigma):
    rng = np.random.default_rng(2)
    T_cw = inv_T(S.camera_path(rng, 1)[0])
    P = np.column_stack([rng.uniform(-2, 2, 30), rng.uniform(-1, 1, 30), rng.uniform(2, 8, 30)])
    Z = np.column_stack([rng.uniform(0, 640, 30), rng.uniform(0, 480, 30), rng.uniform(0, 640, 30)])
    Sf, w = (rng.random(30) < 0.5).astype(float), rng.uniform(0.5, 2.0, 30)
    cam = StereoCamera(S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy, S.CAM.baseline, disparity_sigma)
    args = (np.ascontiguousarray(P.T), np.ascontiguousarray(Z.T), Sf, w, cam, None)
    _, H, g = pose_only._linearize(T_cw[:3, :3], T_cw[:3, 3], *args)
    num = np.zeros(6)
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-6
        costs = []
        for s in (1, -1):
            dR = so3_exp(s * d[:3])
            costs.append(pose_only._linearize(dR @ T_cw[:3, :3], dR @ T_cw[:3, 3] + s * d[3:], *args)[0])
        num[i] = (costs[0] - costs[1]) / 2e-6
    np.testing.assert_allclose(g, num, rtol=1e-5, atol=1e-3)
    assert np.all(np.linalg.eigvalsh(H) > 0)


# --- local BA ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("stereo_frac", [1.0, 0.5, 0.0], ids=["stereo", "mixed", "mono"])
def test_local_ba_recovers_exact_solution(stereo_frac):
    rng = np.random.default_rng(10)
    poses, pts, prob = S.full_scene(rng, stereo_frac=stereo_frac)
    prob.fixed = {0, 1}
    p = S.perturb(rng, prob, trans_m=0.02, rot_deg=1.0, pt_m=0.05)
    fixed_before = {k: p.poses[k].copy() for k in p.fixed}
    r = local_bundle_adjustment(p, S.CAM)
    t, rot, pt = _max_errors(r, poses, pts)
    assert t < 1e-3 and rot < 0.01 and pt < 1e-2
    assert set(r.poses) == set(prob.poses) - {0, 1}  # fixed keyframes are left out ...
    for k, T in fixed_before.items():
        assert np.array_equal(p.poses[k], T)  # ... and the caller's copies are untouched
    assert r.inliers.all()
    assert r.final_error < 1e-6 * r.initial_error
    assert 0 < r.iterations <= 15
    assert {"build", "optimize", "classify", "total"} <= set(r.ms)


@pytest.mark.parametrize("stereo_frac", [1.0, 0.5, 0.0], ids=["stereo", "mixed", "mono"])
def test_local_ba_flags_gross_outliers(stereo_frac):
    rng = np.random.default_rng(11)
    poses, pts, prob = S.full_scene(rng, stereo_frac=stereo_frac)
    prob.fixed = {0, 1}
    bad = S.add_outliers(rng, prob.obs_uv, prob.obs_ur, 0.10, px=30.0)
    # a far-off start (5 cm points, 2 cm / 1 deg poses) with outliers needs more LM iterations than the
    # defaults, which are tuned for SLAM's tracked initial guesses
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM, BackendConfig(max_iterations=10, refine_iterations=5))
    assert np.mean(~r.inliers[bad]) >= 0.95
    assert np.mean(~r.inliers[~bad]) <= 0.02
    # a point left with < 2 inlier views is culled by the caller (ORB-SLAM); judge the others
    n_in = np.bincount(prob.obs_pt[r.inliers], minlength=len(pts))
    t, rot, pt = _max_errors(r, poses, pts, skip_pts=set(np.flatnonzero(n_in < 2).tolist()))
    assert t < 1e-3 and rot < 0.01 and pt < 1e-2
    assert np.mean(n_in < 2) < 0.02


def test_local_ba_point_with_only_outliers_is_dropped_from_the_second_round():
    rng = np.random.default_rng(18)
    poses, pts, prob = S.full_scene(rng, stereo_frac=0.5)
    prob.fixed = {0, 1}
    mine = prob.obs_pt == 0
    prob.obs_uv[mine] += rng.normal(0, 30.0, (mine.sum(), 2))  # every view of point 0 is garbage
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM)
    assert not r.inliers[mine].any() and r.inliers[~mine].all()
    assert np.isfinite(r.points[0]).all()  # kept from the first round, not optimised further
    assert _max_errors(r, poses, pts, skip_pts={0})[0] < 1e-3


def test_local_ba_with_noise_reaches_the_optimum():
    rng = np.random.default_rng(12)
    poses, pts, prob = S.full_scene(rng, stereo_frac=0.5)
    prob.fixed = {0, 1}
    prob.obs_uv += rng.normal(0, 0.5, prob.obs_uv.shape)
    prob.obs_ur += rng.normal(0, 0.5, prob.obs_ur.shape)
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM)
    best = local_bundle_adjustment(prob, S.CAM, BackendConfig(max_iterations=50))  # started at the truth
    assert max(S.pose_error(r.poses[k], best.poses[k])[0] for k in r.poses) < 1e-4
    t, rot, _ = _max_errors(r, poses, pts)
    assert t < 1e-2 and rot < 0.1
    assert np.mean(r.inliers) > 0.99


def test_local_ba_without_fixed_keyframe_holds_the_lowest_id():
    rng = np.random.default_rng(13)
    poses, pts, prob = S.full_scene(rng, n_kf=4, stereo_frac=1.0)
    prob.poses = {k + 5: T for k, T in prob.poses.items()}  # ids need not start at 0
    prob.obs_kf = prob.obs_kf + 5
    p = S.perturb(rng, prob)
    p.poses[5] = poses[0].copy()
    r = local_bundle_adjustment(p, S.CAM)
    assert set(r.poses) == {5, 6, 7, 8}
    assert np.array_equal(r.poses[5], poses[0])  # the gauge anchor comes back unchanged
    assert max(S.pose_error(r.poses[k + 5], poses[k])[0] for k in range(4)) < 1e-3


def test_local_ba_point_seen_only_by_fixed_keyframes_is_optimised():
    rng = np.random.default_rng(14)
    poses, pts, prob = S.full_scene(rng, n_kf=4, stereo_frac=1.0)
    prob.fixed = {0, 1}
    keep = (prob.obs_pt != 0) | (prob.obs_kf <= 1)  # point 0 only in fixed keyframes 0 and 1
    for name in ("obs_kf", "obs_pt", "obs_uv", "obs_ur"):
        setattr(prob, name, getattr(prob, name)[keep])
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM)
    assert np.linalg.norm(r.points[0] - pts[0]) < 1e-6


def test_local_ba_solves_single_view_stereo_points_in_closed_form():
    """A point with one stereo observation says nothing about the poses: the poses come out exactly as without
    it, and the point lands where its measurement back-projects from its keyframe's optimised pose."""
    rng = np.random.default_rng(17)
    poses, pts, prob = S.full_scene(rng, n_kf=5, stereo_frac=0.5)
    prob.fixed = {0}
    prob.obs_uv += rng.normal(0, 0.5, prob.obs_uv.shape)
    prob.obs_ur += rng.normal(0, 0.5, prob.obs_ur.shape)
    base = S.perturb(rng, prob)
    extra = S.perturb(rng, prob)
    extra.poses, extra.points = base.poses, dict(base.points)
    n = len(pts)
    for i, k in enumerate([2, 3, 3, 4]):  # four single-view points; the last one mono (it stays in the graph)
        pc = np.array([0.3 * i - 0.5, 0.2, 5.0 + i])
        pw = poses[k][:3, :3] @ pc + poses[k][:3, 3]
        uv, ur, _ = project_stereo(poses[k], pw[None], S.CAM)
        extra.points[n + i] = pw + rng.normal(0, 0.05, 3)
        extra.obs_kf, extra.obs_pt = np.append(extra.obs_kf, k), np.append(extra.obs_pt, n + i)
        extra.obs_uv = np.vstack([extra.obs_uv, uv + rng.normal(0, 0.5, 2)])
        extra.obs_ur = np.append(extra.obs_ur, np.nan if i == 3 else ur[0] + rng.normal(0, 0.5))
    r0, r1 = local_bundle_adjustment(base, S.CAM), local_bundle_adjustment(extra, S.CAM)
    for k in r0.poses:
        np.testing.assert_allclose(r1.poses[k], r0.poses[k], atol=1e-7)
    for i in range(3):
        k = int(extra.obs_kf[len(prob.obs_kf) + i])
        uv, ur, _ = project_stereo(r1.poses[k], r1.points[n + i][None], S.CAM)
        np.testing.assert_allclose(uv[0], extra.obs_uv[len(prob.obs_kf) + i], atol=1e-8)
        np.testing.assert_allclose(ur[0], extra.obs_ur[len(prob.obs_kf) + i], atol=1e-8)
    assert r1.inliers[len(prob.obs_kf):].all()


def test_local_ba_per_observation_sigma():
    rng = np.random.default_rng(15)
    poses, pts, prob = S.full_scene(rng, stereo_frac=0.0)
    prob.fixed = {0, 1}
    shifted = rng.random(len(prob.obs_kf)) < 0.03
    prob.obs_uv[shifted] += [4.0, 0.0]  # 4 px: an outlier at sigma 1, fine at sigma 2 (chi2 <= 16/4)
    assert np.mean(~local_bundle_adjustment(prob, S.CAM).inliers[shifted]) > 0.8
    prob.obs_sigma = np.where(shifted, 2.0, 1.0)
    r = local_bundle_adjustment(prob, S.CAM)
    assert r.inliers[shifted].all()


def test_local_ba_skips_nan_and_behind_camera_observations():
    rng = np.random.default_rng(16)
    poses, pts, prob = S.full_scene(rng, stereo_frac=0.5)
    prob.fixed = {0, 1}
    prob.obs_uv[3] = np.nan
    prob.points[len(pts)] = poses[2][:3, :3] @ [0.0, 0.0, -3.0] + poses[2][:3, 3]  # behind keyframe 2
    prob.obs_kf = np.append(prob.obs_kf, 2)
    prob.obs_pt = np.append(prob.obs_pt, len(pts))
    prob.obs_uv = np.vstack([prob.obs_uv, [320.0, 240.0]])
    prob.obs_ur = np.append(prob.obs_ur, 300.0)
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM)
    assert not r.inliers[3] and not r.inliers[-1]
    assert r.inliers[:3].all() and r.inliers[4:-1].all()
    assert _max_errors(r, poses, pts, skip_pts={len(pts)})[0] < 1e-3


def test_local_ba_degenerate_inputs():
    cam = S.CAM
    empty = BAProblem({0: np.eye(4)}, {0}, {}, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0))
    r = local_bundle_adjustment(empty, cam)
    assert r.poses == {} and r.points == {} and r.inliers.shape == (0,)
    behind = BAProblem(
        {0: np.eye(4), 1: np.eye(4)}, {0}, {0: np.array([0.0, 0.0, -2.0]), 1: np.array([1.0, 0.0, -5.0])},
        np.array([0, 1, 1]), np.array([0, 0, 1]), np.full((3, 2), 300.0), np.array([np.nan, 290.0, np.nan]),
    )
    r = local_bundle_adjustment(behind, cam)
    assert not r.inliers.any()
    assert np.array_equal(r.poses[1], np.eye(4)) and np.array_equal(r.points[1], [1.0, 0.0, -5.0])
    with pytest.raises(ValueError, match="unknown"):
        local_bundle_adjustment(BAProblem({0: np.eye(4)}, set(), {}, np.array([0]), np.array([9]),
                                          np.zeros((1, 2)), np.zeros(1)), cam)


def test_local_ba_mono_camera_ignores_ur():
    rng = np.random.default_rng(17)
    poses, pts, prob = S.full_scene(rng, stereo_frac=1.0)
    prob.fixed = {0, 1}
    prob.obs_ur[:] = 0.0  # garbage that a zero-baseline camera must ignore
    mono_cam = StereoCamera(S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy, 0.0)
    r = local_bundle_adjustment(S.perturb(rng, prob), mono_cam)
    assert r.inliers.all() and _max_errors(r, poses, pts)[0] < 1e-3


# --- pose-only ---------------------------------------------------------------------------------------


def _pose_problem(rng, n, stereo_frac, outliers):
    T, pw, uv, ur = S.pose_problem(rng, n, stereo_frac)
    bad = S.add_outliers(rng, uv, ur, outliers)
    return T, pw, uv, ur, bad


@pytest.mark.parametrize("stereo_frac", [1.0, 0.5, 0.0], ids=["stereo", "mixed", "mono"])
def test_optimize_pose_recovers_pose_and_flags_outliers(stereo_frac):
    rng = np.random.default_rng(20)
    T, pw, uv, ur, bad = _pose_problem(rng, 300, stereo_frac, 0.20)
    T0 = S.perturb_pose(rng, T, 0.03, 2.0)
    Te, inl = optimize_pose(T0, pw, uv, ur, S.CAM)
    dt, dr = S.pose_error(Te, T)
    assert dt < 2e-3 and dr < 0.05
    assert not inl[bad].any() and inl[~bad].all()


def test_optimize_pose_with_noise_and_per_point_sigma():
    rng = np.random.default_rng(21)
    T, pw, uv, ur, bad = _pose_problem(rng, 300, 0.5, 0.20)
    sigma = np.where(rng.random(300) < 0.3, 1.44, 1.0)  # e.g. two pyramid levels
    uv += rng.normal(0, 0.4, uv.shape) * sigma[:, None]
    ur += rng.normal(0, 0.4, 300) * sigma
    Te, inl = optimize_pose(S.perturb_pose(rng, T, 0.03, 2.0), pw, uv, ur, S.CAM, BackendConfig(), sigma=sigma)
    dt, dr = S.pose_error(Te, T)
    assert dt < 5e-3 and dr < 0.05
    assert np.mean(~inl[bad]) >= 0.95 and np.mean(~inl[~bad]) <= 0.02


def test_optimize_pose_lets_a_rejected_point_come_back():
    rng = np.random.default_rng(22)
    T, pw, uv, ur, bad = _pose_problem(rng, 100, 0.5, 0.3)
    T0 = S.perturb_pose(rng, T, 0.10, 3.0)
    one = BackendConfig(pose_rounds=1, pose_iterations=2)  # the Huber-biased first round rejects good points ...
    _, inl = optimize_pose(T0, pw, uv, ur, S.CAM, one)
    assert np.mean(inl[~bad]) < 0.95
    Te, inl = optimize_pose(T0, pw, uv, ur, S.CAM, BackendConfig(pose_iterations=2))  # ... later rounds take them back
    assert inl[~bad].all() and not inl[bad].any()
    assert S.pose_error(Te, T)[0] < 1e-6


def test_optimize_pose_degenerate_inputs():
    T = np.eye(4)
    Te, inl = optimize_pose(T, np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0), S.CAM)
    assert np.array_equal(Te, T) and inl.shape == (0,)
    pw = np.array([[0.0, 0.0, -3.0], [1.0, 0.0, -4.0], [0.0, 1.0, -5.0], [1.0, 1.0, -6.0]])  # all behind
    Te, inl = optimize_pose(T, pw, np.full((4, 2), 300.0), np.full(4, np.nan), S.CAM)
    assert np.array_equal(Te, T) and not inl.any()
    Te, inl = optimize_pose(T, pw[:2] * [1, 1, -1], np.full((2, 2), 300.0), np.full(2, np.nan), S.CAM)
    assert np.array_equal(Te, T) and inl.shape == (2,)
    rng = np.random.default_rng(23)
    Tt, pw, uv, ur, _ = _pose_problem(rng, 50, 0.5, 0.0)
    uv[:5] = np.nan
    Te, inl = optimize_pose(Tt, pw, uv, ur, S.CAM)
    assert not inl[:5].any() and inl[5:].all() and S.pose_error(Te, Tt)[0] < 1e-9


def test_rgbd_depth_outlier_can_stay_a_mono_observation():
    """With ``rgbd_depth_outliers_as_mono`` an RGB-D observation whose depth is wrong but whose pixel is right is
    reported in ``depth_only`` (kept as mono by ``Map.apply_adjustment``); a wrong pixel is not."""
    rgbd = StereoCamera(S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy, S.CAM.baseline, disparity_sigma=0.1)
    rng = np.random.default_rng(11)
    _, _, prob = S.full_scene(rng, n_kf=4, n_pts=80, stereo_frac=1.0)
    prob.fixed = {0, 1}
    bad_depth, bad_pixel = 5, 9
    prob.obs_ur[bad_depth] += 3.0  # the disparity is 3 px off, the pixel exact
    prob.obs_uv[bad_pixel] += 6.0
    prob.obs_ur[bad_pixel] += 6.0
    off = local_bundle_adjustment(prob, rgbd)
    assert off.depth_only is None and not off.inliers[bad_depth] and not off.inliers[bad_pixel]
    on = local_bundle_adjustment(prob, rgbd, BackendConfig(rgbd_depth_outliers_as_mono=True))
    assert on.depth_only[bad_depth] and not on.depth_only[bad_pixel]
    assert not on.depth_only[on.inliers].any() and on.depth_only.sum() <= 2


def _linked_scene(rng, link_error_m: float = 0.0):
    """full_scene whose keyframe 5 observes nothing (a dense-step keyframe: too few features), tied to keyframe 4
    by a PoseLink (1 mm / 0.05 deg); everything but keyframes 0 and 1 perturbed."""
    from vslam.mapping.map import PoseLink

    poses, pts, prob = S.full_scene(rng, stereo_frac=0.5)
    prob.fixed = {0, 1}
    keep = prob.obs_kf != 5
    prob.obs_kf, prob.obs_pt, prob.obs_uv, prob.obs_ur = (a[keep] for a in (prob.obs_kf, prob.obs_pt, prob.obs_uv, prob.obs_ur))
    T45 = inv_T(poses[4]) @ poses[5]
    T45[:3, 3] += np.array([link_error_m, 0.0, 0.0])
    cov = np.diag(np.r_[np.full(3, np.radians(0.05)), np.full(3, 1e-3)] ** 2)
    p = S.perturb(rng, prob, trans_m=0.03, rot_deg=1.5, pt_m=0.05)
    return poses, pts, p, PoseLink(4, 5, T45, cov)


def test_local_ba_pose_link_places_a_keyframe_without_observations():
    rng = np.random.default_rng(31)
    poses, pts, p, link = _linked_scene(rng)
    start5 = p.poses[5].copy()
    r0 = local_bundle_adjustment(p, S.CAM)
    np.testing.assert_array_equal(r0.poses[5], start5)  # nothing measures it: returned unchanged
    p.links = [link]
    r = local_bundle_adjustment(p, S.CAM)
    t, rot, pt = _max_errors(r, poses, pts)
    assert t < 1e-3 and rot < 0.01 and pt < 1e-2  # keyframe 5 included: placed by its link to the adjusted 4
    assert S.pose_error(start5, poses[5])[0] > 0.02


def test_local_ba_wrong_pose_link_is_bounded_by_the_observations():
    """A link 0.3 m wrong (300 sigma) moves the well-observed keyframe 4 by well under a millimetre (Huber)."""
    rng = np.random.default_rng(32)
    poses, pts, p, link = _linked_scene(rng, link_error_m=0.3)
    p.links = [link]
    r = local_bundle_adjustment(p, S.CAM)
    for k in (2, 3, 4):
        assert S.pose_error(r.poses[k], poses[k])[0] < 5e-4
    assert abs(S.pose_error(r.poses[5], poses[5])[0] - 0.3) < 0.01  # the link is all keyframe 5 has


def test_local_ba_pose_links_alone_still_place_their_keyframes():
    """No multi-view observation at all, only links: the linked keyframe is still placed by them (the early
    returns for observation-free windows do not drop the links)."""
    from vslam.mapping.map import PoseLink

    T0 = make_T(np.eye(3), np.zeros(3))
    T1 = make_T(so3_exp(np.array([0.0, 0.1, 0.0])), np.array([0.3, 0.0, 0.1]))
    cov = np.eye(6) * 1e-6
    empty = np.zeros(0, np.int64)
    p = BAProblem({0: T0, 1: T1 @ make_T(np.eye(3), np.array([0.05, 0.0, 0.0]))}, {0}, {}, empty, empty,
                  np.zeros((0, 2)), np.zeros(0), links=[PoseLink(0, 1, inv_T(T0) @ T1, cov)])
    r = local_bundle_adjustment(p, S.CAM)
    np.testing.assert_allclose(r.poses[1], T1, atol=1e-6)
