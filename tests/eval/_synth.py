"""Synthetic trajectories with exactly known errors, shared by the eval tests."""

from __future__ import annotations

import numpy as np

from vslam.data.trajectory import Trajectory
from vslam.geometry.se3 import make_T, so3_exp


def curvy(n: int = 60, dt: float = 0.1, length_scale: float = 1.0) -> Trajectory:
    """A non-planar, turning path (so Umeyama is well posed), timestamps dt apart."""
    s = np.linspace(0.0, 2.0 * np.pi, n)
    xyz = length_scale * np.stack([np.cos(s) * 3.0, np.sin(2 * s) * 2.0, 0.5 * s + 0.3 * np.sin(3 * s)], axis=1)
    poses = np.stack([make_T(so3_exp([0.1 * np.sin(a), 0.2 * a, 0.05 * a]), p) for a, p in zip(s, xyz)])
    return Trajectory(np.arange(n) * dt + 100.0, poses)


def line(n: int, step: float = 1.0, dt: float = 0.1) -> Trajectory:
    """Constant velocity along x: pose i at (i*step, 0, 0), identity rotation."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step
    return Trajectory(np.arange(n) * dt, poses)


def transformed(traj: Trajectory, T: np.ndarray, scale: float = 1.0) -> Trajectory:
    """World-frame similarity applied to every pose: p -> s R p + t, R_i -> R R_i."""
    poses = traj.poses.copy()
    poses[:, :3, 3] = scale * np.einsum("ij,nj->ni", T[:3, :3], poses[:, :3, 3]) + T[:3, 3]
    poses[:, :3, :3] = T[:3, :3] @ poses[:, :3, :3]
    return Trajectory(traj.timestamps.copy(), poses)
