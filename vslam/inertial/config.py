"""Typed settings of the inertial stage (preintegration noise, time offset, initialisation).

Plain field types so ``vslam.config.from_dict`` builds it from a YAML
``inertial:`` block; ``None`` noise fields mean "take the value from the
calibration (EuRoC/TUM-VI imu0 sensor.yaml)".
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from vslam.data.types import ImuNoise
from vslam.errors import ConfigError


@dataclass(frozen=True)
class InertialConfig:
    """IMU preintegration and initialisation settings.

    gravity: magnitude in m/s^2, world z up (gtsam ``MakeSharedU``).
    *_noise_density / *_random_walk: continuous-time Kalibr densities; None = from calibration.
    noise_scale: multiplies all four densities (inflating datasheet values is common practice).
    t_offset_s: IMU-camera clock offset, t_imu = t_cam + t_offset_s.
    integration_sigma: gtsam integration (discretisation) noise sigma, m/s^2 per sqrt(Hz)-ish; keeps covariances PD.
    static_window_s: length of the still window used by static initialisation, s.
    still_accel_std / still_gyro_std: per-axis std thresholds (m/s^2, rad/s) of the smoothed signals above
        which a window is "moving"; still_smooth_s: that moving-average length (removes rotor vibration).
    still_max_force_error: allowed | |mean specific force| - g | in a still window, m/s^2.
    prior_accel_bias_sigma / prior_gyro_bias_sigma: bias prior sigmas for the first bias state (m/s^2, rad/s).
    prior_velocity_sigma: velocity prior sigma after static init, m/s.
    accel_range / gyro_range: the sensor's full scale (m/s^2, rad/s); a reading at or beyond it is clipped or
        corrupt and is dropped (``vslam.inertial.gate``). The defaults, 16 g and 2000 deg/s, are the largest
        ranges of the common MEMS IMUs (MPU-6000/9250, ICM-20602/42688, BMI088's gyro); a dataset config
        narrows them to its sensor (EuRoC's ADIS16448: 18 g, 1000 deg/s).
    spike_window / spike_sigmas / spike_floor_accel / spike_floor_gyro: the Hampel spike test
        (``vslam.inertial.gate``): samples each side, MAD-scale multiple, absolute floors (m/s^2, rad/s).
        The floors, 3 g and 5 rad/s, are ~4.5x and ~16x the largest departure of a clean EuRoC sample from its
        neighbours' median (rotor vibration, k = 5), so real vibration passes.
    max_gap_s: a longer hole between accepted samples is not integrated: the inertial factors are off over
        it (``vslam.tracking.vio``), s.
    """

    gravity: float = 9.81
    gyro_noise_density: float | None = None
    gyro_random_walk: float | None = None
    accel_noise_density: float | None = None
    accel_random_walk: float | None = None
    noise_scale: float = 1.0
    t_offset_s: float = 0.0
    integration_sigma: float = 1e-4
    static_window_s: float = 2.0
    still_accel_std: float = 0.1
    still_gyro_std: float = 0.01
    still_smooth_s: float = 0.2
    still_max_force_error: float = 0.5
    prior_accel_bias_sigma: float = 0.1
    prior_gyro_bias_sigma: float = 0.01
    prior_velocity_sigma: float = 0.05
    accel_range: float = 16.0 * 9.80665
    gyro_range: float = float(np.radians(2000.0))
    spike_window: int = 5
    spike_sigmas: float = 10.0
    spike_floor_accel: float = 30.0
    spike_floor_gyro: float = 5.0
    max_gap_s: float = 0.05

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "t_offset_s" or v is None:
                continue
            if not v > 0:
                raise ConfigError(f"inertial.{f.name} must be positive, got {v!r}")

    def noise(self, calibrated: ImuNoise | None) -> ImuNoise:
        """The ImuNoise to use: calibration values (or EuRoC defaults) with this config's overrides and scale."""
        base = calibrated if calibrated is not None else ImuNoise()
        s = self.noise_scale

        def pick(name: str) -> float:
            own = getattr(self, name)
            return s * float(own if own is not None else getattr(base, name))

        return ImuNoise(
            gyro_noise_density=pick("gyro_noise_density"),
            gyro_random_walk=pick("gyro_random_walk"),
            accel_noise_density=pick("accel_noise_density"),
            accel_random_walk=pick("accel_random_walk"),
            rate_hz=base.rate_hz,
        )

    def imu_time(self, t_cam: float) -> float:
        """Camera timestamp -> IMU clock (s)."""
        return float(t_cam) + self.t_offset_s
