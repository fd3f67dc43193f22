"""The IMU noise-model fit recovers known densities and a known starting-bias error on synthetic data."""

from __future__ import annotations

import numpy as np

from tests.inertial._synth import synthetic_imu
from vslam.data.types import ImuNoise
from vslam.inertial.evaluate import ImuNoiseModel, fit_noise_model, nees, window_residuals

# std of the error of the "ground-truth" biases handed to the windows: at 1 s as large as the white noise's effect
GYRO_BIAS_ERR, ACCEL_BIAS_ERR = 2e-4, 2e-3


def test_fit_recovers_densities_and_bias_error() -> None:
    cfg, _, imu, truth = synthetic_imu(120.0, noise=True, seed=3)
    rng = np.random.default_rng(1)
    # A bias error constant over 0.5 s blocks: each window start draws its own (window starts fall on blocks).
    block = np.floor((truth.t - truth.t[0]) / 0.5 + 1e-6).astype(int)
    bg = truth.gyro_bias + rng.normal(0, GYRO_BIAS_ERR, (block.max() + 1, 3))[block]
    ba = truth.accel_bias + rng.normal(0, ACCEL_BIAS_ERR, (block.max() + 1, 3))[block]
    sets = [window_residuals(imu, truth.t, truth.T_world_body, truth.v_world, ba, bg, cfg.imu_noise, L)
            for L in (0.5, 1.0, 2.0)]
    n = cfg.imu_noise
    datasheet = ImuNoiseModel(n.gyro_noise_density, n.accel_noise_density, 1e-9, 1e-9)
    assert np.mean(nees(sets[2], datasheet)) > 12  # the bias error is invisible to the sensor noise alone (measured 16)
    m = fit_noise_model(sets, ImuNoiseModel(3 * n.gyro_noise_density, 3 * n.accel_noise_density, 1e-4, 1e-3))
    assert abs(m.gyro_noise_density / n.gyro_noise_density - 1) < 0.3, m
    assert abs(m.accel_noise_density / n.accel_noise_density - 1) < 0.3, m
    assert abs(m.gyro_bias_sigma / GYRO_BIAS_ERR - 1) < 0.3, m
    assert abs(m.accel_bias_sigma / ACCEL_BIAS_ERR - 1) < 0.3, m
    for r in sets:
        assert 4.0 < np.mean(nees(r, m)) < 8.0


def test_residual_covariance_is_linear_in_the_densities() -> None:
    """C_gyro / C_accel scale with density^2: the fitted model's covariance equals gtsam's at those densities."""
    from vslam.inertial.preintegration import make_bias, make_params, preintegrate

    cfg, _, imu, truth = synthetic_imu(3.0, noise=True)
    r = window_residuals(imu, truth.t, truth.T_world_body, truth.v_world, truth.accel_bias, truth.gyro_bias,
                         cfg.imu_noise, 1.0)
    n = cfg.imu_noise
    C = ImuNoiseModel(n.gyro_noise_density, n.accel_noise_density, 0.0, 0.0).covariance(r)[0]
    pim = preintegrate(imu, truth.t[0], truth.t[0] + 1.0, make_params(n), make_bias(truth.accel_bias[0], truth.gyro_bias[0]))
    np.testing.assert_allclose(C, pim.preintMeasCov()[:6, :6], rtol=1e-6, atol=1e-14)
