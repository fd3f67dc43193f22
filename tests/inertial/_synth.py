"""Synthetic IMU + exact truth for the inertial tests (no rendering: the analytic motion only)."""

from __future__ import annotations

import numpy as np

from vslam.data.synthetic.config import SyntheticConfig
from vslam.data.synthetic.imu import ImuTruth, microsecond_grid, synthesize_imu
from vslam.data.synthetic.motion import RigMotion, build_motion
from vslam.data.types import ImuSamples


def synthetic_imu(seconds: float, noise: bool, seed: int = 0, rate: float = 200.0) -> tuple[SyntheticConfig, RigMotion, ImuSamples, ImuTruth]:
    """A room trajectory of ``seconds`` with its IMU at ``rate`` Hz (EuRoC noise levels when ``noise``)."""
    cfg = SyntheticConfig(n_frames=max(2, int(seconds * 30) + 1), imu_noise_enabled=noise, seed=seed, imu_rate=rate)
    motion = build_motion(cfg)
    imu, truth = synthesize_imu(cfg, motion, microsecond_grid(int(round(seconds * rate)) + 1, rate))
    return cfg, motion, imu, truth
