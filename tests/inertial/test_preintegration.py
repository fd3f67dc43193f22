"""Preintegration against exact trajectories (synthetic generator, gtsam ScenarioRunner), tiling, errors, NEES."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from tests.inertial._synth import synthetic_imu
from vslam.data.types import ImuNoise, ImuSamples
from vslam.errors import ConfigError, InertialError
from vslam.geometry.se3 import so3_log
from vslam.inertial import InertialConfig, make_bias, make_params, preintegrate, predict
from vslam.inertial.evaluate import window_errors


def _errors(motion, cfg, imu, t0: float, t1: float) -> tuple[float, float, float]:
    """(position m, rotation deg, velocity m/s) error of predicting the true state at t1 from the one at t0."""
    s = motion.body_state(np.array([t0, t1]) - cfg.start_time)
    bias = make_bias(cfg.accel_bias, cfg.gyro_bias)
    pim = preintegrate(imu, t0, t1, make_params(cfg.imu_noise), bias)
    R, p, v = predict((s.R[0], s.p[0], s.v[0]), bias, pim)
    return (float(np.linalg.norm(p - s.p[1])), float(np.degrees(np.linalg.norm(so3_log(R.T @ s.R[1])))),
            float(np.linalg.norm(v - s.v[1])))


def test_noise_free_synthetic_matches_truth_and_converges_with_rate() -> None:
    cfg, motion, imu, _ = synthetic_imu(2.0, noise=False)
    # Window ends off the sample grid: the bounds are interpolated, not snapped.
    t0, t1 = imu.t[40] + 0.0013, imu.t[240] - 0.0021
    pos, rot, vel = _errors(motion, cfg, imu, t0, t1)
    assert pos < 1e-3 and rot < 2e-3 and vel < 3e-3, (pos, rot, vel)
    # The remaining error is gtsam's first-order step, not a bug: 5x the rate cuts it >= 3x.
    cfg5, motion5, imu5, _ = synthetic_imu(2.0, noise=False, rate=1000.0)
    pos5, rot5, vel5 = _errors(motion5, cfg5, imu5, t0, t1)
    assert pos5 < pos / 3 and rot5 < rot / 3 and vel5 < vel / 3, (pos5, rot5, vel5)


def test_constant_twist_against_gtsam_scenario_runner() -> None:
    noise = ImuNoise()
    params = make_params(noise)
    scenario = gtsam.ConstantTwistScenario(np.array([0.1, -0.2, 0.4]), np.array([1.0, 0.2, -0.1]))
    true_bias = make_bias(np.array([0.05, -0.02, 0.03]), np.array([0.003, 0.001, -0.002]))
    runner = gtsam.ScenarioRunner(scenario, params, 0.005, true_bias)
    t = np.arange(0, 401) * 0.005
    # actual* + bias: gtsam's measured* also add random noise.
    imu = ImuSamples(t, np.array([runner.actualAngularVelocity(x) for x in t]) + true_bias.gyroscope(),
                     np.array([runner.actualSpecificForce(x) for x in t]) + true_bias.accelerometer())
    pim = preintegrate(imu, 0.0, 2.0, params, true_bias)
    R, p, v = predict(scenario.navState(0.0), true_bias, pim)
    truth = scenario.navState(2.0)
    err_p, err_v = np.linalg.norm(p - truth.position()), np.linalg.norm(v - truth.velocity())
    assert np.linalg.norm(so3_log(R.T @ truth.attitude().matrix())) < 1e-9
    assert err_p < 2e-4 and err_v < 2e-4, (err_p, err_v)
    # gtsam's own sample-and-hold integration of the same measurements is first order: ~1.7 cm off here.
    ref = runner.predict(runner.integrate(2.0, true_bias, False), true_bias)
    assert np.linalg.norm(ref.position() - truth.position()) > 50 * err_p


def test_consecutive_windows_tile_one_long_window() -> None:
    cfg, motion, imu, _ = synthetic_imu(2.0, noise=True)
    params, bias = make_params(cfg.imu_noise), make_bias(cfg.accel_bias, cfg.gyro_bias)
    s0 = motion.body_state(np.array([imu.t[10] - cfg.start_time]))
    state = (s0.R[0], s0.p[0], s0.v[0])
    t0, tm, t1 = imu.t[10], imu.t[150] + 0.0017, imu.t[300]  # split inside a sample interval
    a, b = preintegrate(imu, t0, tm, params, bias), preintegrate(imu, tm, t1, params, bias)
    whole = preintegrate(imu, t0, t1, params, bias)
    assert a.deltaTij() + b.deltaTij() == pytest.approx(t1 - t0, abs=1e-12)
    R2, p2, v2 = predict(predict(state, bias, a), bias, b)
    R1, p1, v1 = predict(state, bias, whole)
    # Splitting one sample interval only moves where inside it the (noisy) acceleration acts: O(|Δa| dt^2).
    assert np.linalg.norm(p2 - p1) < 2e-5
    assert np.linalg.norm(so3_log(R1.T @ R2)) < 2e-5  # gtsam integrates rotation in a tangent chart: O(dt) terms
    assert np.linalg.norm(v2 - v1) < 1e-4
    # A gap or overlap of one sample would move the end by ~|v| * 5 ms, 100x the tolerance above.
    assert np.linalg.norm(s0.v[0]) * 0.005 > 100 * 2e-5


def test_uncovered_window_and_gaps_are_clear_errors() -> None:
    _, _, imu, _ = synthetic_imu(1.0, noise=False)
    params, bias = make_params(ImuNoise()), make_bias()
    with pytest.raises(InertialError, match="do not cover"):
        preintegrate(imu, imu.t[0] - 0.01, imu.t[50], params, bias)
    with pytest.raises(InertialError, match="do not cover"):
        preintegrate(imu, imu.t[100], imu.t[-1] + 0.001, params, bias)
    with pytest.raises(InertialError, match="t1 must be after t0"):
        preintegrate(imu, imu.t[5], imu.t[5], params, bias)
    keep = np.r_[0:50, 70:len(imu.t)]  # a 0.1 s hole
    holed = ImuSamples(imu.t[keep], imu.gyro[keep], imu.accel[keep])
    with pytest.raises(InertialError, match="gap"):
        preintegrate(holed, imu.t[10], imu.t[100], params, bias)
    preintegrate(holed, imu.t[10], imu.t[100], params, bias, max_gap_s=0.2)  # allowed when asked for


def test_params_take_continuous_densities_squared() -> None:
    noise = ImuNoise(1e-4, 2e-5, 3e-3, 4e-4)
    p = make_params(noise, 9.8, T_body_sensor=np.eye(4), integration_sigma=1e-3)
    assert np.allclose(p.getGyroscopeCovariance(), np.eye(3) * 1e-8)
    assert np.allclose(p.getAccelerometerCovariance(), np.eye(3) * 9e-6)
    assert np.allclose(p.getBiasOmegaCovariance(), np.eye(3) * 4e-10)
    assert np.allclose(p.getBiasAccCovariance(), np.eye(3) * 1.6e-7)
    assert np.allclose(p.n_gravity, [0, 0, -9.8])
    merged = InertialConfig(accel_noise_density=0.01, noise_scale=2.0).noise(noise)
    assert merged.accel_noise_density == pytest.approx(0.02) and merged.gyro_noise_density == pytest.approx(2e-4)
    with pytest.raises(ConfigError, match="inertial.noise_scale must be positive"):
        InertialConfig(noise_scale=0.0)


def test_nees_is_consistent_on_synthetic_noise() -> None:
    """With noise drawn from exactly the modelled densities, the 6-dof NEES must average ~6."""
    cfg, _, imu, truth = synthetic_imu(40.0, noise=True, seed=3)
    sub = slice(0, None, 10)  # 20 Hz truth, like EuRoC's ground truth here
    res = window_errors(imu, truth.t[sub], truth.T_world_body[sub], truth.v_world[sub], truth.accel_bias[sub],
                        truth.gyro_bias[sub], cfg.imu_noise, length_s=1.0)
    assert len(res.nees) == 40
    assert 4.5 < np.mean(res.nees) < 7.5, np.mean(res.nees)
    # Ten times too optimistic a model would be caught: NEES scales with 1/density^2.
    tight = ImuNoise(*(np.array([cfg.imu_noise.gyro_noise_density, cfg.imu_noise.gyro_random_walk,
                                 cfg.imu_noise.accel_noise_density, cfg.imu_noise.accel_random_walk]) / 3), 200.0)
    res_tight = window_errors(imu, truth.t[sub], truth.T_world_body[sub], truth.v_world[sub], truth.accel_bias[sub],
                              truth.gyro_bias[sub], tight, length_s=1.0)
    assert np.mean(res_tight.nees) > 30
