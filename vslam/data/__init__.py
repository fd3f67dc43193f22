"""Sequences, frames, calibration and trajectories; dataset readers live beside this file."""

from vslam.data.trajectory import Trajectory, TrajectoryWriter, read_trajectory, write_trajectory
from vslam.data.types import Calibration, Frame, ImuNoise, ImuSamples, PinholeCamera, Sequence

__all__ = [
    "Calibration",
    "Frame",
    "ImuNoise",
    "ImuSamples",
    "PinholeCamera",
    "Sequence",
    "Trajectory",
    "TrajectoryWriter",
    "read_trajectory",
    "write_trajectory",
]
