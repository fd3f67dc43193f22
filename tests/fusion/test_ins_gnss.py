"""INS/GNSS: seed-000 error model structure, simulator sanity, tightly coupled filters on a short run."""

from __future__ import annotations

import dataclasses

import numpy as np

from vslam.fusion.ins_gnss import InsGnssConfig, error_model_F, monte_carlo, run_filter, simulate_run
from vslam.fusion.simulate import GnssConfig, TrajectoryConfig, drifting_vo_track, simulate_truth


def _short(noise="mixture", mp=0.05, outages=((30.0, 38.0, 0),)) -> InsGnssConfig:
    g = dataclasses.replace(GnssConfig(), noise=noise, multipath_prob=mp, outages=outages)
    return InsGnssConfig(trajectory=TrajectoryConfig(duration_s=60.0), gnss=g, runs=2, filters=("ekf", "ckf", "arsckf"))


def test_error_model_blocks_follow_seed_000_eq6():
    C = np.eye(3)
    F = error_model_F(np.zeros(3), C, np.array([0, 9.8, 0]), np.deg2rad(54.0), specific_force_coupling=False)
    assert F.shape == (17, 17)
    np.testing.assert_array_equal(F[0:3, 3:6], np.eye(3))  # F_INS1
    np.testing.assert_array_equal(F[3:6, 9:12], C)  # F_INS3
    np.testing.assert_array_equal(F[6:9, 12:15], C)  # F_INS4
    assert np.all(F[9:15] == 0) and F[3, 5] == -2 * 7.2922115e-5 * np.sin(np.deg2rad(54.0))  # Coriolis term
    assert np.all(F[3:6, 6:9] == 0)
    Fc = error_model_F(np.zeros(3), C, np.array([0, 9.8, 0]), 0.9)
    assert Fc[3, 8] != 0 and Fc[5, 6] != 0  # gravity couples tilt into horizontal velocity error


def test_truth_is_consistent_with_imu():
    tr = simulate_truth(TrajectoryConfig(duration_s=20.0))
    speed = np.linalg.norm(tr.v[:, [0, 2]], axis=1)
    np.testing.assert_allclose(speed, 12.0, atol=0.05)
    assert np.allclose(np.linalg.det(tr.C), 1.0)


def test_gaussian_run_is_accurate_and_consistent():
    cfg = _short(noise="gaussian", mp=0.0, outages=())
    truth, f, w, gnss = simulate_run(cfg, np.random.default_rng(3))
    r = run_filter("ckf", truth, f, w, gnss, cfg, np.random.default_rng(4))
    late = r.t > 20
    assert np.sqrt(np.mean(np.sum(r.pos_err[late] ** 2, 1))) < 4.0  # 8 sats, 3 m pseudoranges
    assert 0.6 < np.nanmean(r.nis[late]) < 1.5  # NIS / m ~ 1 when the model is right
    sig = np.sqrt(np.trace(r.pos_cov[late], axis1=1, axis2=2))
    assert 0.3 < np.mean(np.linalg.norm(r.pos_err[late], axis=1) / sig) < 2.0


def test_robust_filter_beats_ekf_and_ckf_with_outliers():
    res = monte_carlo(_short(), seed=0)
    assert abs(res["ekf"]["pos_rms"] - res["ckf"]["pos_rms"]) < 0.05 * res["ckf"]["pos_rms"]
    assert res["arsckf"]["pos_rms"] < 0.8 * res["ckf"]["pos_rms"]


def test_vo_track_drifts_with_distance():
    tr = simulate_truth(TrajectoryConfig(duration_s=100.0))
    vo = drifting_vo_track(tr.t, tr.p, np.random.default_rng(0), drift_per_m=0.01)
    err = np.linalg.norm(vo - tr.p, axis=1)
    assert err[:10].mean() < 0.5 and 1.0 < err[-1] < 30.0
