"""Trajectories (timestamped camera poses) and their file formats.

Formats: ``tum`` (``t tx ty tz qx qy qz qw``), ``kitti`` (12 numbers = the top
3x4 of T_world_cam per line, no timestamps; an optional times.txt gives them),
``euroc`` (ASL csv: ``t[ns], px, py, pz, qw, qx, qy, qz, ...``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TextIO

import numpy as np

from vslam.data.textio import check_increasing, check_rotations, check_unit_quaternions, read_numeric, require_file
from vslam.errors import DatasetError
from vslam.geometry.se3 import R_to_quat_wxyz, quat_wxyz_to_R

TrajFormat = Literal["tum", "kitti", "euroc"]
FORMATS: tuple[str, ...] = ("tum", "kitti", "euroc")


@dataclass
class Trajectory:
    """timestamps (N,) float64 seconds; poses (N,4,4) float64 T_world_cam."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps for {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def path_length(self) -> float:
        """Sum of distances between consecutive positions, metres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())

    def subset(self, idx: np.ndarray) -> Trajectory:
        return Trajectory(self.timestamps[idx], self.poses[idx])

    def nearest(self, t: np.ndarray, max_diff: float) -> np.ndarray:
        """For each query time, the index of the nearest pose within max_diff seconds, else -1."""
        t = np.asarray(t, dtype=np.float64)
        if len(self) == 0:
            return np.full(len(t), -1, dtype=np.int64)
        j = np.clip(np.searchsorted(self.timestamps, t), 1, len(self) - 1) if len(self) > 1 else np.zeros(len(t), int)
        if len(self) > 1:
            left_closer = np.abs(t - self.timestamps[j - 1]) <= np.abs(self.timestamps[j] - t)
            j = np.where(left_closer, j - 1, j)
        ok = np.abs(self.timestamps[j] - t) <= max_diff
        return np.where(ok, j, -1).astype(np.int64)


def guess_format(path: Path) -> TrajFormat:
    """Format from the extension and the first data line's shape."""
    path = Path(path)
    require_file(path, "trajectory file")
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if "," in s:
            return "euroc"
        n = len(s.split())
        if n == 12:
            return "kitti"
        if n == 8:
            return "tum"
        raise DatasetError(path, f"cannot tell the trajectory format from a line of {n} columns (tum: 8, kitti: 12, euroc: csv)")
    raise DatasetError(path, "trajectory file has no poses")


def read_trajectory(path: str | Path, fmt: str = "auto", times: str | Path | None = None) -> Trajectory:
    """Read a trajectory file; KITTI poses get timestamps from ``times`` or their row index."""
    path = Path(path)
    fmt = guess_format(path) if fmt == "auto" else fmt
    if fmt == "tum":
        lines, v = read_numeric(path, 8)
        check_unit_quaternions(path, v[:, 4:8], lines, first_col=5)
        t = v[:, 0]
        R = quat_wxyz_to_R(v[:, [7, 4, 5, 6]]) if len(v) else np.zeros((0, 3, 3))
        poses = _poses(R, v[:, 1:4])
    elif fmt == "kitti":
        lines, v = read_numeric(path, 12)
        poses = np.tile(np.eye(4), (len(v), 1, 1))
        poses[:, :3, :4] = v.reshape(-1, 3, 4)
        check_rotations(path, poses[:, :3, :3], lines)
        if times is not None:
            tl, tv = read_numeric(Path(times), 1)
            if len(tv) < len(v):
                raise DatasetError(Path(times), f"has {len(tv)} times for {len(v)} poses in {path}")
            t = tv[: len(v), 0]
        else:
            t = np.arange(len(v), dtype=np.float64)
    elif fmt == "euroc":
        lines, v = read_numeric(path, (8, 64), delimiter=",")
        t = v[:, 0] * 1e-9  # the ASL format stores nanoseconds
        check_unit_quaternions(path, v[:, 4:8], lines, first_col=5)
        R = quat_wxyz_to_R(v[:, 4:8]) if len(v) else np.zeros((0, 3, 3))
        poses = _poses(R, v[:, 1:4])
    else:
        raise DatasetError(path, f"unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)}")
    if len(t) == 0:
        raise DatasetError(path, "trajectory file has no poses")
    check_increasing(path, t, lines)
    return Trajectory(t, poses)


def _poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = R
    poses[:, :3, 3] = t
    return poses


def format_pose(t: float, T: np.ndarray, fmt: str) -> str:
    """One line (no newline) of a trajectory file."""
    if fmt == "tum":
        q = R_to_quat_wxyz(T[:3, :3])
        p = T[:3, 3]
        return f"{t:.6f} {p[0]:.9f} {p[1]:.9f} {p[2]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f} {q[0]:.9f}"
    if fmt == "kitti":
        return " ".join(f"{x:.9e}" for x in T[:3, :4].reshape(-1))
    if fmt == "euroc":
        q = R_to_quat_wxyz(T[:3, :3])
        p = T[:3, 3]
        return f"{int(round(t * 1e9))},{p[0]:.9f},{p[1]:.9f},{p[2]:.9f},{q[0]:.9f},{q[1]:.9f},{q[2]:.9f},{q[3]:.9f}"
    raise ValueError(f"unknown trajectory format {fmt!r}")


def write_trajectory(path: str | Path, traj: Trajectory, fmt: str = "tum") -> Path:
    """The whole trajectory at once, through a temporary file: complete or absent, never cut."""
    from vslam.outputs import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp, TrajectoryWriter(tmp, fmt) as w:
        for t, T in zip(traj.timestamps, traj.poses):
            w.write(float(t), T)
    return path


def kitti_times_path(path: str | Path) -> Path:
    """The times file written beside a KITTI pose file: ``trajectory.kitti.txt`` -> ``trajectory.kitti.times.txt``."""
    path = Path(path)
    return path.with_name(path.name[: -len(path.suffix)] + ".times" + path.suffix if path.suffix else path.name + ".times")


class TrajectoryWriter:
    """Appends poses to a file as they are produced and flushes each line,
    so a crash or Ctrl-C never loses the trajectory computed so far.

    KITTI pose files have no time column and a run does not pose every frame (a monocular map starts after its
    first frames, a lost frame has no pose): the times of the written poses go, line for line, to
    ``kitti_times_path(path)`` (KITTI's times.txt format) so the file can be matched by time, not by row.
    """

    def __init__(self, path: str | Path, fmt: str = "tum"):
        if fmt not in FORMATS:
            raise ValueError(f"unknown trajectory format {fmt!r}")
        self.path = Path(path)
        self.fmt = fmt
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: TextIO | None = open(self.path, "w")
        self.times_path = kitti_times_path(self.path) if fmt == "kitti" else None
        try:
            self._times: TextIO | None = open(self.times_path, "w") if self.times_path is not None else None
        except BaseException:
            self._f.close()
            raise
        if fmt == "tum":
            self._f.write("# timestamp tx ty tz qx qy qz qw\n")
        elif fmt == "euroc":
            self._f.write("#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []\n")
        self._f.flush()

    def write(self, t: float, T_world_cam: np.ndarray) -> None:
        assert self._f is not None, "writer is closed"
        self._f.write(format_pose(t, T_world_cam, self.fmt) + "\n")
        self._f.flush()
        if self._times is not None:
            self._times.write(f"{t:.6f}\n")
            self._times.flush()

    def close(self) -> None:
        try:
            if self._f is not None:
                f, self._f = self._f, None
                f.close()
        finally:
            if self._times is not None:
                t, self._times = self._times, None
                t.close()

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
