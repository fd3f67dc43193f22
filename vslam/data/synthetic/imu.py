"""Exact IMU measurements from the analytic rig motion, plus the truth behind them.

Measurement model (body frame = IMU frame, Kalibr / EuRoC convention):

    gyro_k  = omega_body(t_k) + b_g(t_k) + n_g,   n_g ~ N(0, sigma_g^2 / dt)
    accel_k = R_world_body^T (a_world - g) + b_a(t_k) + n_a,   g = (0, 0, -9.81)
    b(t_k+1) = b(t_k) + sigma_b * sqrt(dt) * N(0, 1)

(the discretisation of continuous white noise and of a Wiener-process bias,
Kalibr wiki "IMU Noise Model"). With ``imu_noise_enabled=False`` both noise
terms are zero and the biases stay at their initial values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vslam.data.synthetic.config import SyntheticConfig
from vslam.data.synthetic.motion import GRAVITY, RigMotion
from vslam.data.types import ImuSamples


@dataclass
class ImuTruth:
    """What produced each IMU sample; all arrays have N rows, world frame z up.

    t: (N,) s. T_world_body: (N,4,4). v_world, a_world: (N,3) m/s, m/s^2.
    omega_body: (N,3) rad/s, true angular velocity. gyro_bias: (N,3) rad/s and
    accel_bias: (N,3) m/s^2, the biases inside each measurement.
    """

    t: np.ndarray
    T_world_body: np.ndarray
    v_world: np.ndarray
    a_world: np.ndarray
    omega_body: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def microsecond_grid(n: int, rate: float) -> np.ndarray:
    """(n,) int64 microseconds k * 1e6 / rate, rounded.

    Whole microseconds make every stamp exactly representable in the "%.6f"
    seconds of TUM files and the integer nanoseconds of ASL files.
    """
    return np.round(np.arange(n) * (1e6 / rate)).astype(np.int64)


def imu_grid_us(cfg: SyntheticConfig, last_frame_us: int) -> np.ndarray:
    """IMU sample times from frame 0 up to (and covering) the last frame, microseconds."""
    n = int(np.ceil(last_frame_us * 1e-6 * cfg.imu_rate - 1e-9)) + 1
    return microsecond_grid(n, cfg.imu_rate)


def synthesize_imu(cfg: SyntheticConfig, motion: RigMotion, t_us: np.ndarray) -> tuple[ImuSamples, ImuTruth]:
    """Measurements and truth at ``t_us`` (microseconds since frame 0); seeded by cfg.seed."""
    tau = t_us * 1e-6
    state = motion.body_state(tau)
    n = len(tau)
    f_body = np.einsum("nji,nj->ni", state.R, state.a - GRAVITY)  # R^T (a - g): specific force
    bg = np.tile(np.asarray(cfg.gyro_bias, dtype=np.float64), (n, 1))
    ba = np.tile(np.asarray(cfg.accel_bias, dtype=np.float64), (n, 1))
    gyro, accel = state.omega_body + bg, f_body + ba
    if cfg.imu_noise_enabled:
        rng = np.random.default_rng([cfg.seed, 2])  # stream 2: IMU noise
        noise = cfg.imu_noise
        dt = 1.0 / cfg.imu_rate
        white_g = rng.standard_normal((n, 3)) * (noise.gyro_noise_density / np.sqrt(dt))
        white_a = rng.standard_normal((n, 3)) * (noise.accel_noise_density / np.sqrt(dt))
        steps_g = rng.standard_normal((n, 3)) * (noise.gyro_random_walk * np.sqrt(dt))
        steps_a = rng.standard_normal((n, 3)) * (noise.accel_random_walk * np.sqrt(dt))
        steps_g[0] = steps_a[0] = 0.0  # the first sample carries the configured initial bias
        bg = bg + np.cumsum(steps_g, axis=0)
        ba = ba + np.cumsum(steps_a, axis=0)
        gyro = state.omega_body + bg + white_g
        accel = f_body + ba + white_a
    t = cfg.start_time + tau
    truth = ImuTruth(t, state.T_world_body, state.v, state.a, state.omega_body, bg, ba)
    return ImuSamples(t.copy(), gyro, accel), truth
