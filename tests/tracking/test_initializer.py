import cv2
import numpy as np
import pytest

from vslam.geometry.se3 import make_T, so3_exp
from vslam.tracking.initializer import (
    InitConfig,
    TwoViewResult,
    initialize_two_view,
    score_fundamental,
    score_homography,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
MOTION = make_T(so3_exp([0.02, -0.08, 0.03]), [-1.0, 0.1, 0.2])  # T_cur_ref: ~5 deg, 1 m sideways
LATERAL = make_T(so3_exp([0.02, -0.08, 0.03]), [-2.0, 0.1, 0.0])  # for the plane: no forward component


def _project(T_c_ref: np.ndarray, P_ref: np.ndarray):
    p = P_ref @ T_c_ref[:3, :3].T + T_c_ref[:3, 3]
    return p[:, :2] / p[:, 2:3] @ K[:2, :2].T + K[:2, 2], p[:, 2]


def _scene(seed, T_cur_ref, n=500, planar=False, noise=0.5, outliers=0.2, zrange=(4.0, 12.0)):
    """n points (reference frame) visible in both views, noisy pixels, a fraction of the current
    pixels replaced by random ones. Returns uv_ref, uv_cur, P_ref, is_outlier."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [W, H], (6 * n, 2))
    rays = np.hstack([uv, np.ones((len(uv), 1))]) @ np.linalg.inv(K).T
    if planar:  # plane n.X = -6 m in the reference frame, tilted about x
        normal = np.array([0.0, -0.3, -1.0]) / np.hypot(0.3, 1.0)
        P = rays * (-6.0 / (rays @ normal))[:, None]
    else:
        P = rays * rng.uniform(*zrange, len(uv))[:, None]
    uv2, z2 = _project(T_cur_ref, P)
    P = P[(z2 > 0.1) & np.all((uv2 >= 0) & (uv2 < [W, H]), axis=1)][:n]
    assert len(P) == n
    uv_ref = _project(np.eye(4), P)[0] + rng.normal(0.0, noise, (n, 2))
    uv_cur = _project(T_cur_ref, P)[0] + rng.normal(0.0, noise, (n, 2))
    is_out = np.zeros(n, bool)
    is_out[rng.choice(n, int(outliers * n), replace=False)] = True
    uv_cur[is_out] = rng.uniform([0, 0], [W, H], (is_out.sum(), 2))
    return uv_ref, uv_cur, P, is_out


def _motion_errors_deg(T_est, T_gt):
    dR = T_est[:3, :3].T @ T_gt[:3, :3]
    rot = np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0)))
    a, b = T_est[:3, 3], T_gt[:3, 3]
    tdir = np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0)))
    return rot, tdir


def _check_reconstruction(r: TwoViewResult, P, is_out, uv_cur):
    """Shared invariants: scale, frames, points vs ground truth, few outliers accepted."""
    good = r.inliers
    assert np.isfinite(r.pts_ref[good]).all() and np.isnan(r.pts_ref[~good]).all()
    assert np.median(r.pts_ref[good, 2]) == pytest.approx(1.0, abs=1e-12)
    # T_cur_ref maps reference-frame points into the current camera: they reproject onto uv_cur
    uv, z = _project(r.T_cur_ref, r.pts_ref[good])
    assert (z > 0).all() and np.linalg.norm(uv - uv_cur[good], axis=1).max() <= 2.0 + 1e-9
    # points equal the ground truth up to the one global scale (true median depth)
    scale = np.median(P[good, 2])
    rel = np.linalg.norm(r.pts_ref[good] * scale - P[good], axis=1) / np.linalg.norm(P[good], axis=1)
    assert np.median(rel) < 0.03
    assert good.sum() >= 0.9 * (~is_out).sum() and (good & is_out).sum() <= 0.01 * good.sum()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_general_scene_selects_essential_and_recovers_motion(seed):
    uv_ref, uv_cur, P, is_out = _scene(seed, MOTION)
    r = initialize_two_view(uv_ref, uv_cur, K)
    assert r is not None and r.model == "essential"
    assert r.score_ratio < 0.45 and r.support[1] < 0.1 * r.support[0]
    rot, tdir = _motion_errors_deg(r.T_cur_ref, MOTION)
    assert rot < 0.1 and tdir < 1.0
    assert r.parallax_deg > 3.0
    _check_reconstruction(r, P, is_out, uv_cur)


@pytest.mark.parametrize("seed", [0, 1])
def test_planar_scene_selects_homography_and_recovers_motion(seed):
    uv_ref, uv_cur, P, is_out = _scene(seed, LATERAL, planar=True)
    r = initialize_two_view(uv_ref, uv_cur, K)
    assert r is not None and r.model == "homography" and r.score_ratio > 0.45
    rot, tdir = _motion_errors_deg(r.T_cur_ref, LATERAL)
    assert rot < 0.25 and tdir < 1.0
    _check_reconstruction(r, P, is_out, uv_cur)


def test_planar_scenes_are_never_initialised_wrongly():
    # A plane fits two motions (and two essential matrices) equally well. Whatever the motion and
    # noise, the initializer must either find the true one or refuse. Without the H-inlier-ratio
    # test (cfg.planar_inlier_ratio) two of these scenes come back as "essential", 45-67 deg off.
    rng = np.random.default_rng(7)
    accepted = 0
    for seed in range(12):
        t = rng.normal(size=3)
        T = make_T(so3_exp(rng.normal(0.0, 0.08, 3)), t * rng.uniform(0.5, 2.0) / np.linalg.norm(t))
        uv_ref, uv_cur, _, _ = _scene(100 + seed, T, planar=True, noise=rng.uniform(0.3, 1.0))
        r = initialize_two_view(uv_ref, uv_cur, K)
        if r is not None:
            accepted += 1
            rot, tdir = _motion_errors_deg(r.T_cur_ref, T)
            assert rot < 0.5 and tdir < 3.0, (seed, r.model, rot, tdir)
    assert accepted >= 1  # the acceptance path is exercised too


@pytest.mark.parametrize("t", [np.zeros(3), np.array([0.004, -0.002, 0.001])], ids=["pure_rotation", "tiny_baseline"])
@pytest.mark.parametrize("planar", [False, True])
def test_no_parallax_is_refused(t, planar):
    T = make_T(so3_exp([0.03, -0.1, 0.02]), t)
    uv_ref, uv_cur, _, _ = _scene(3, T, planar=planar)
    assert initialize_two_view(uv_ref, uv_cur, K) is None


def test_min_parallax_threshold_is_applied():
    uv_ref, uv_cur, _, _ = _scene(4, MOTION)
    r = initialize_two_view(uv_ref, uv_cur, K)
    assert r is not None
    assert initialize_two_view(uv_ref, uv_cur, K, InitConfig(min_parallax_deg=r.parallax_deg + 0.1)) is None


def test_bad_inputs_are_refused():
    rng = np.random.default_rng(5)
    uv = rng.uniform([0, 0], [W, H], (300, 2))
    assert initialize_two_view(uv, rng.uniform([0, 0], [W, H], (300, 2)), K) is None  # random matches
    assert initialize_two_view(uv, uv.copy(), K) is None  # no motion at all
    assert initialize_two_view(uv[:50], uv[:50] + 3.0, K) is None  # fewer than min_matches
    assert initialize_two_view(np.zeros((0, 2)), np.zeros((0, 2)), K) is None
    with pytest.raises(ValueError):
        initialize_two_view(uv, uv[:-1], K)
    with pytest.raises(ValueError):
        initialize_two_view(np.full((300, 2), np.nan), uv, K)


def test_deterministic_and_independent_of_global_rng():
    uv_ref, uv_cur, _, _ = _scene(6, MOTION, outliers=0.4)
    r1 = initialize_two_view(uv_ref, uv_cur, K)
    cv2.setRNGSeed(12345)
    np.random.seed(999)
    r2 = initialize_two_view(uv_ref, uv_cur, K)
    assert r1 is not None and r2 is not None
    np.testing.assert_array_equal(r1.T_cur_ref, r2.T_cur_ref)
    np.testing.assert_array_equal(r1.inliers, r2.inliers)


def test_scores_on_exact_models():
    uv_ref, _, P, _ = _scene(8, MOTION, noise=0.0, outliers=0.0, n=200)
    uv_cur = _project(MOTION, P)[0]
    Hm, _ = cv2.findHomography(uv_ref, uv_cur, 0)  # least squares: wrong for a 3-D scene
    R, t = MOTION[:3, :3], MOTION[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(K)
    s_f, in_f = score_fundamental(Ki.T @ tx @ R @ Ki, uv_ref, uv_cur, 1.0)
    s_h, in_h = score_homography(Hm, uv_ref, uv_cur, 1.0)
    assert in_f.all() and s_f == pytest.approx(2 * 5.991 * 200, rel=1e-9)  # zero error: full score
    assert in_h.mean() < 0.5 and s_h < 0.5 * s_f
