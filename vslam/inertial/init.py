"""Inertial initialisation: static (still window) here, visual-inertial alignment in ``alignment``.

Static initialisation (the EuRoC pre-takeoff window is exactly this case): at
rest the accelerometer reads the specific force -R_world_body^T g, so its mean
gives the body's roll and pitch, and the mean gyro reading is the gyro bias.
Yaw is unobservable from gravity and is set to 0. Only the accelerometer bias
component *along* gravity is observable (as |mean force| - g); the components
perpendicular to it are indistinguishable from a tilt (1 cm/s^2 of such bias
tilts the estimate by 0.06 deg), so they are reported as zero unless a prior
(a calibration or an earlier session's estimate) is given. On EuRoC V1_01 the
ground-truth bias has ~0.07 m/s^2 perpendicular to gravity, i.e. ~0.4 deg of
tilt that no still window can separate from attitude.

The still test runs on a moving average of the signals: rotor vibration
(EuRoC V1_01: raw accelerometer std up to 1 m/s^2 with the MAV sitting on the
floor) is high-frequency, motion is not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vslam.data.types import ImuSamples
from vslam.errors import InertialError
from vslam.inertial.alignment import ViAlignment, vi_align

__all__ = ["StaticInit", "ViAlignment", "gravity_aligned_rotation", "static_init", "vi_align"]

MIN_STATIC_SAMPLES = 20


@dataclass(frozen=True)
class StaticInit:
    """Result of a still-window initialisation; world z up, gravity (0, 0, -g).

    R_world_body: (3,3) roll/pitch from gravity, yaw = 0.
    gyro_bias: (3,) rad/s, the mean gyro reading (Earth rate, 7.3e-5 rad/s, is not removed).
    accel_bias: (3,) m/s^2, the prior (zeros without one) plus the component along gravity (see module doc).
    gravity_world: (3,) m/s^2, (0, 0, -g).
    up_body: (3,) unit vector, world up expressed in the body frame (the mean specific force direction).
    accel_std, gyro_std: (3,) per-axis std of the smoothed signals (what the still test compares).
    force_norm_error: |mean specific force| - g, m/s^2.
    still: whether the window passed the still test; ``reason`` says why not.
    """

    t0: float
    t1: float
    n_samples: int
    R_world_body: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    gravity_world: np.ndarray
    up_body: np.ndarray
    accel_std: np.ndarray
    gyro_std: np.ndarray
    force_norm_error: float
    still: bool
    reason: str = ""

    def require_still(self) -> StaticInit:
        """Self, or InertialError with the reason when the window was moving."""
        if not self.still:
            raise InertialError(f"static initialisation over [{self.t0:.3f}, {self.t1:.3f}] s rejected: {self.reason}")
        return self


def gravity_aligned_rotation(up_body: np.ndarray) -> np.ndarray:
    """R_world_body (3,3) with zero yaw (ZYX Euler) that maps the body vector ``up_body`` to world +z."""
    u = np.asarray(up_body, dtype=np.float64)
    u = u / np.linalg.norm(u)
    # R = Rz(0) Ry(pitch) Rx(roll) and R^T e_z = (-sin p, cos p sin r, cos p cos r).
    pitch = np.arctan2(-u[0], np.hypot(u[1], u[2]))
    roll = np.arctan2(u[1], u[2])
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return Ry @ Rx


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or len(x) <= n:
        return x
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    return (c[n:] - c[:-n]) / n


def static_init(
    imu: ImuSamples,
    t0: float,
    t1: float,
    gravity: float = 9.81,
    still_accel_std: float = 0.1,
    still_gyro_std: float = 0.01,
    smooth_s: float = 0.2,
    max_force_error: float = 0.5,
    accel_bias_prior: np.ndarray | None = None,
) -> StaticInit:
    """Initialise attitude and gyro bias from the samples with t0 <= t <= t1 (IMU clock, s).

    The window is "still" when every axis of the ``smooth_s`` moving average
    has std below ``still_accel_std`` (m/s^2) and ``still_gyro_std`` (rad/s),
    and | |mean force| - g | < ``max_force_error``. A moving window still gets
    its numbers, with still=False and the reason; call ``require_still()`` to
    turn that into an error. accel_bias_prior: (3,) m/s^2 removed from the
    readings first; its component along gravity is then re-estimated.
    """
    t = np.asarray(imu.t)
    m = (t >= t0) & (t <= t1)
    n = int(m.sum())
    if n < MIN_STATIC_SAMPLES:
        raise InertialError(f"static window [{t0:.3f}, {t1:.3f}] s holds {n} IMU samples; need at least {MIN_STATIC_SAMPLES}")
    acc, gyr = imu.accel[m], imu.gyro[m]
    prior = np.zeros(3) if accel_bias_prior is None else np.asarray(accel_bias_prior, dtype=np.float64).reshape(3)
    f_mean, w_mean = acc.mean(axis=0) - prior, gyr.mean(axis=0)
    f_norm = float(np.linalg.norm(f_mean))
    up = f_mean / f_norm
    rate = (n - 1) / max(float(t[m][-1] - t[m][0]), 1e-9)
    k = max(1, int(round(smooth_s * rate)))
    a_std, g_std = _moving_average(acc, k).std(axis=0), _moving_average(gyr, k).std(axis=0)

    reasons = []
    if np.max(g_std) > still_gyro_std:
        reasons.append(f"gyro std {np.max(g_std):.4f} rad/s > {still_gyro_std} (smoothed over {smooth_s} s)")
    if np.max(a_std) > still_accel_std:
        reasons.append(f"accel std {np.max(a_std):.3f} m/s^2 > {still_accel_std} (smoothed over {smooth_s} s)")
    if abs(f_norm - gravity) > max_force_error:
        reasons.append(f"mean specific force {f_norm:.3f} m/s^2 differs from g = {gravity} by more than {max_force_error}")
    return StaticInit(
        t0=float(t0),
        t1=float(t1),
        n_samples=n,
        R_world_body=gravity_aligned_rotation(up),
        gyro_bias=w_mean,
        accel_bias=prior + (f_norm - gravity) * up,
        gravity_world=np.array([0.0, 0.0, -gravity]),
        up_body=up,
        accel_std=a_std,
        gyro_std=g_std,
        force_norm_error=f_norm - gravity,
        still=not reasons,
        reason="; ".join(reasons),
    )
