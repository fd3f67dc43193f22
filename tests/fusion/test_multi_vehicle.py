"""Multi-vehicle fusion (seed 004): vector KF vs two-stage."""

from __future__ import annotations

import dataclasses

import numpy as np

from vslam.fusion.multi_vehicle import (
    GroupConfig, observation_matrix, rms_pos_vel, simulate_estimates, two_stage_cov, vector_kf_cov,
)


def test_observation_matrix_rows():
    C = observation_matrix(3)
    assert C.shape == (9, 3)
    np.testing.assert_array_equal(C[0], [1, 0, 0])  # own z^1
    np.testing.assert_array_equal(C[1], [1, -1, 0])  # mutual z^12 = x^1 - x^2


def test_agree_when_mutual_measurements_are_exact():
    cfg = GroupConfig(M=6, sigma_mut=1e-4, sigma_vmut=1e-5, a_x=0.0, steps=60)
    vp, vv = rms_pos_vel(vector_kf_cov(cfg), cfg.M)
    sp, sv = rms_pos_vel(two_stage_cov(cfg)[1], cfg.M)
    np.testing.assert_allclose(vp, sp, rtol=1e-2)  # the transient differs slightly (prior)
    np.testing.assert_allclose(vp[-20:], sp[-20:], rtol=1e-3)  # the steady state agrees
    np.testing.assert_allclose(vv[-20:], sv[-20:], rtol=1e-3)


def test_vector_kf_better_with_disturbance_and_noisy_mutual():
    cfg = GroupConfig(M=6, sigma_v=1.0, sigma_mut=1.0, sigma_vmut=1.0, a_x=1.0, steps=60)
    vp, _ = rms_pos_vel(vector_kf_cov(cfg), cfg.M)
    own, true = two_stage_cov(cfg)
    sp, _ = rms_pos_vel(true, cfg.M)
    assert vp[-1] < 0.97 * sp[-1]
    np.testing.assert_allclose(np.diagonal(own, axis1=1, axis2=2), np.diagonal(true, axis1=1, axis2=2), rtol=1e-9)


def test_covariance_matches_monte_carlo():
    cfg = GroupConfig(M=4, steps=40)
    errs = [simulate_estimates(cfg, np.random.default_rng(s)) for s in range(60)]
    vp, _ = rms_pos_vel(vector_kf_cov(cfg), cfg.M)
    mc = np.sqrt(np.mean([np.mean(e["vector"][-1, :cfg.M] ** 2) for e in errs]))
    assert abs(mc - vp[-1]) < 0.2 * vp[-1]


def test_more_vehicles_and_velocity_help():
    base = GroupConfig(steps=60)
    small, big = (rms_pos_vel(vector_kf_cov(dataclasses.replace(base, M=M)), M)[0][-1] for M in (2, 10))
    nov = rms_pos_vel(vector_kf_cov(dataclasses.replace(base, M=10, use_velocity=False)), 10)[0][-1]
    assert big < 0.7 * small and big < nov
