"""KITTI odometry metric (t_rel, r_rel), as the official devkit computes it.

Geiger et al., "Are we ready for autonomous driving? The KITTI vision benchmark
suite", CVPR 2012; devkit ``evaluate_odometry.cpp`` (``trajectoryDistances``,
``lastFrameFromSegmentLength``, ``calcSequenceErrors``, ``rotationError``,
``translationError``). evo has no equivalent: ``evo_rpe -d 100 -u m`` picks
different segments and does not divide by the length.

The algorithm, step by step as in the devkit:
  1. cumulative GT path distance per frame;
  2. for every ``step``-th first frame and each length L (100..800 m), the last
     frame is the first one whose distance exceeds dist[first] + L (strictly,
     ``>``); segments running past the end are skipped;
  3. pose_error = inv(est_rel) @ gt_rel with x_rel = inv(x[first]) @ x[last];
  4. r_err = angle(pose_error) / L, t_err = |translation(pose_error)| / L;
  5. average over all segments (and per length).
No alignment is applied, as in the devkit: relative poses are invariant to a
rigid transform of the whole estimate, but not to its scale.
Deviations: float64 instead of the devkit's float32; r_rel is reported in
deg/100 m (the devkit's stats.txt holds rad/m and its plots deg/m) and t_rel in
percent. The step of 10 frames means "every second" at KITTI's 10 Hz.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from vslam.geometry.se3 import inv_T


@dataclass(frozen=True)
class KittiLengthError:
    """Average over the segments of one length: t_rel (%), r_rel (deg/100 m), segment count."""

    length: float
    t_rel: float
    r_rel: float
    n_segments: int


@dataclass(frozen=True)
class KittiOdometryError:
    """t_rel: mean translation error in % of segment length; r_rel: mean rotation error in deg/100 m."""

    t_rel: float
    r_rel: float
    n_segments: int
    per_length: tuple[KittiLengthError, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "t_rel_percent": self.t_rel,
            "r_rel_deg_per_100m": self.r_rel,
            "n_segments": self.n_segments,
            "per_length": [
                {"length_m": p.length, "t_rel_percent": p.t_rel, "r_rel_deg_per_100m": p.r_rel, "n_segments": p.n_segments}
                for p in self.per_length
            ],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> KittiOdometryError:
        per = tuple(
            KittiLengthError(p["length_m"], p["t_rel_percent"], p["r_rel_deg_per_100m"], p["n_segments"]) for p in d["per_length"]
        )
        return cls(d["t_rel_percent"], d["r_rel_deg_per_100m"], d["n_segments"], per)


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """(N,4,4) poses -> (N,) cumulative path distance in metres, 0 at the first frame."""
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def segment_errors(
    gt: np.ndarray, est: np.ndarray, lengths: tuple[float, ...], step: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All devkit segments: (lengths (M,), t_err (M,) per metre, r_err (M,) rad per metre).

    gt, est: (N,4,4) T_world_cam of matched frames.
    """
    dist = trajectory_distances(gt)
    n = len(dist)
    first = np.arange(0, n, step)
    seg_len, t_err, r_err = [], [], []
    for L in lengths:
        # First frame with dist > dist[first] + L (devkit's strict '>'); dist is non-decreasing.
        last = np.searchsorted(dist, dist[first] + L, side="right")
        ok = last < n
        f, l = first[ok], last[ok]
        if len(f) == 0:
            continue
        gt_rel = inv_T(gt[f]) @ gt[l]
        est_rel = inv_T(est[f]) @ est[l]
        err = inv_T(est_rel) @ gt_rel
        cos = 0.5 * (np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0)
        r_err.append(np.arccos(np.clip(cos, -1.0, 1.0)) / L)
        t_err.append(np.linalg.norm(err[:, :3, 3], axis=1) / L)
        seg_len.append(np.full(len(f), L))
    if not seg_len:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(seg_len), np.concatenate(t_err), np.concatenate(r_err)


def kitti_odometry_error(
    gt: np.ndarray,
    est: np.ndarray,
    lengths: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0),
    step: int = 10,
) -> tuple[KittiOdometryError | None, str | None]:
    """(metric, None), or (None, reason) when no segment fits (GT path shorter than the shortest length).

    gt, est: (N,4,4) T_world_cam, frame i of both at the same instant; metres.
    """
    gt = np.asarray(gt, dtype=np.float64)
    est = np.asarray(est, dtype=np.float64)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"need two (N,4,4) pose stacks of equal N, got {gt.shape} and {est.shape}")
    if len(gt) < 2:
        return None, f"not applicable: {len(gt)} matched poses"
    seg_len, t_err, r_err = segment_errors(gt, est, tuple(lengths), step)
    if len(seg_len) == 0:
        total = float(trajectory_distances(gt)[-1])
        return None, (
            f"not applicable: the ground-truth path is {total:.1f} m long; "
            f"KITTI segments need more than {min(lengths):g} m"
        )
    per = []
    for L in lengths:
        sel = seg_len == L
        if sel.any():
            per.append(KittiLengthError(float(L), _pct(t_err[sel]), _deg100(r_err[sel]), int(sel.sum())))
    return KittiOdometryError(_pct(t_err), _deg100(r_err), int(len(seg_len)), tuple(per)), None


def _pct(t_err_per_m: np.ndarray) -> float:
    return float(np.mean(t_err_per_m) * 100.0)


def _deg100(r_err_rad_per_m: np.ndarray) -> float:
    return float(np.degrees(np.mean(r_err_rad_per_m)) * 100.0)
