"""Local BA's numpy Schur-complement solver (``BackendConfig.solver = "numpy"``, ``vslam.backend.schur``): the
same estimate as the GTSAM graph, and the behaviours ``test_ba`` checks for GTSAM."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.backend import _synth as S
from vslam.backend import ba as ba_mod
from vslam.backend.ba import BackendConfig, local_bundle_adjustment

NUMPY = BackendConfig(solver="numpy")
GTSAM = BackendConfig(solver="gtsam")


def _noisy_window(seed: int, stereo_frac: float, outliers: float = 0.05):
    rng = np.random.default_rng(seed)
    poses, pts, prob = S.window(rng, n_kf=8, obs_per_kf=200, stereo_frac=stereo_frac, views=3)
    prob.fixed = {0, 1}
    prob.obs_uv += rng.normal(0.0, 0.5, prob.obs_uv.shape)
    prob.obs_ur += rng.normal(0.0, 0.5, prob.obs_ur.shape)
    S.add_outliers(rng, prob.obs_uv, prob.obs_ur, outliers)
    return poses, pts, S.perturb(rng, prob, trans_m=0.005, rot_deg=0.2, pt_m=0.01)  # SLAM: tracked starts


@pytest.mark.parametrize("stereo_frac,disparity_sigma", [(0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (0.7, 0.1)],
                         ids=["mono", "mixed", "stereo", "rgbd"])
def test_numpy_solver_matches_gtsam(stereo_frac, disparity_sigma):
    _, _, p = _noisy_window(3, stereo_frac)
    cam = dataclasses.replace(S.CAM, disparity_sigma=disparity_sigma)
    g = local_bundle_adjustment(p, cam, GTSAM)
    n = local_bundle_adjustment(p, cam, NUMPY)
    assert set(n.poses) == set(g.poses) and n.iterations == g.iterations
    for k in g.poses:
        dt, dr = S.pose_error(n.poses[k], g.poses[k])
        assert dt < 1e-4 and dr < 1e-3  # metres, degrees: the two LM paths differ only in rounding and retraction
    dp = np.array([np.linalg.norm(n.points[j] - g.points[j]) for j in g.points])
    # the worst: a mono point of little parallax. The median is what rounding leaves after the same 6 LM steps:
    # measured 8.2e-6 m here (mono), 2.5e-6..1.07e-5 m over window seeds 0-7 (0.1-1.5e-6 with stereo or depth);
    # a different cost or Jacobian in one solver leaves the ~1 cm start perturbation, orders of magnitude more
    assert np.median(dp) < 5e-5 and dp.max() < 1e-2, (np.median(dp), dp.max())
    assert np.mean(n.inliers == g.inliers) > 0.998
    assert n.initial_error == pytest.approx(g.initial_error, rel=1e-9)
    assert n.final_error == pytest.approx(g.final_error, rel=1e-3)
    assert n.final_error < 0.9 * n.initial_error  # (the outliers keep most of it)


@pytest.mark.parametrize("stereo_frac", [1.0, 0.5, 0.0], ids=["stereo", "mixed", "mono"])
def test_numpy_solver_recovers_the_exact_solution(stereo_frac):
    rng = np.random.default_rng(10)
    poses, pts, prob = S.full_scene(rng, stereo_frac=stereo_frac)
    prob.fixed = {0, 1}
    r = local_bundle_adjustment(S.perturb(rng, prob, trans_m=0.02, rot_deg=1.0, pt_m=0.05), S.CAM, NUMPY)
    assert set(r.poses) == set(prob.poses) - {0, 1}
    assert max(S.pose_error(r.poses[k], poses[k])[0] for k in r.poses) < 1e-3
    assert max(S.pose_error(r.poses[k], poses[k])[1] for k in r.poses) < 0.01
    assert max(np.linalg.norm(r.points[j] - pts[j]) for j in r.points) < 1e-2
    assert r.inliers.all() and r.final_error < 1e-6 * r.initial_error


def test_numpy_solver_flags_gross_outliers():
    rng = np.random.default_rng(11)
    _, _, prob = S.full_scene(rng, stereo_frac=0.5)
    prob.fixed = {0, 1}
    bad = S.add_outliers(rng, prob.obs_uv, prob.obs_ur, 0.10, px=30.0)
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM, dataclasses.replace(NUMPY, max_iterations=10, refine_iterations=5))
    assert np.mean(~r.inliers[bad]) >= 0.95 and np.mean(~r.inliers[~bad]) <= 0.02


def test_numpy_solver_holds_the_lowest_id_without_fixed_keyframes():
    rng = np.random.default_rng(13)
    poses, _, prob = S.full_scene(rng, n_kf=4, stereo_frac=1.0)
    p = S.perturb(rng, prob)
    p.poses[0] = poses[0].copy()
    r = local_bundle_adjustment(p, S.CAM, dataclasses.replace(NUMPY, max_iterations=20))
    assert set(r.poses) == {0, 1, 2, 3}
    assert np.array_equal(r.poses[0], poses[0])  # the gauge anchor comes back unchanged
    assert max(S.pose_error(r.poses[k], poses[k])[0] for k in range(4)) < 1e-3


def test_numpy_solver_optimises_a_point_seen_only_by_fixed_keyframes():
    rng = np.random.default_rng(14)
    _, pts, prob = S.full_scene(rng, n_kf=4, stereo_frac=1.0)
    prob.fixed = {0, 1}
    keep = (prob.obs_pt != 0) | (prob.obs_kf <= 1)
    for name in ("obs_kf", "obs_pt", "obs_uv", "obs_ur"):
        setattr(prob, name, getattr(prob, name)[keep])
    r = local_bundle_adjustment(S.perturb(rng, prob), S.CAM, NUMPY)
    assert np.linalg.norm(r.points[0] - pts[0]) < 1e-6


def test_numpy_solver_hands_large_windows_to_gtsam(monkeypatch):
    _, _, p = _noisy_window(5, 0.5)
    monkeypatch.setattr(ba_mod, "NUMPY_MAX_POSES", 4)  # 8 keyframes: over the limit
    n = local_bundle_adjustment(p, S.CAM, NUMPY)
    g = local_bundle_adjustment(p, S.CAM, GTSAM)
    assert all(np.array_equal(n.poses[k], g.poses[k]) for k in g.poses)  # the same code ran
    monkeypatch.setattr(ba_mod, "NUMPY_MAX_POSES", 24)
    assert any(not np.array_equal(local_bundle_adjustment(p, S.CAM, NUMPY).poses[k], g.poses[k]) for k in g.poses)
