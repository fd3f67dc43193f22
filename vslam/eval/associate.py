"""Pair estimated poses with ground-truth poses, and convert to/from evo types.

Timestamped trajectories are associated exactly as ``evo_ape`` does it
(``evo.core.sync.associate_trajectories``, nearest stamp within ``max_diff``),
so our numbers equal the CLI's. KITTI pose files carry no timestamps; they are
matched line by line, as the KITTI devkit and ``evo_ape kitti`` do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from evo.core import sync
from evo.core.trajectory import PoseTrajectory3D

from vslam.data.trajectory import Trajectory
from vslam.errors import EvalError

MIN_MATCHES = 3  # Umeyama needs 3 non-collinear points to fix a rotation.


@dataclass
class Association:
    """Matched pairs: ``gt[i]`` and ``est[i]`` are the same instant.

    gt, est: the matched poses, each keeping its own timestamps (seconds, or
    line indices when ``by_index`` and the files had no times).
    """

    gt: Trajectory
    est: Trajectory
    by_index: bool

    def __len__(self) -> int:
        return len(self.gt)


def to_evo(traj: Trajectory, name: str | None = None) -> PoseTrajectory3D:
    # Copies: evo aligns trajectories in place, and the caller's poses must stay untouched.
    return PoseTrajectory3D(poses_se3=list(traj.poses.copy()), timestamps=traj.timestamps.copy(), name=name)


def from_evo(traj: PoseTrajectory3D) -> Trajectory:
    return Trajectory(np.asarray(traj.timestamps, dtype=np.float64), np.asarray(traj.poses_se3, dtype=np.float64))


def associate(
    est: Trajectory,
    gt: Trajectory,
    max_diff: float,
    *,
    by_index: bool = False,
    est_name: str = "the estimate",
    gt_name: str = "the ground truth",
) -> Association:
    """Match poses by timestamp (evo's nearest-stamp rule) or, for KITTI files, by line."""
    if by_index:
        if len(est) != len(gt):
            raise EvalError(
                f"{est_name} has {len(est)} poses and {gt_name} {len(gt)}; poses without timestamps are "
                "matched line by line, so both must have the same length (or give a times file)"
            )
        _check_count(len(est), est_name, gt_name, "matched line by line")
        return Association(gt=gt, est=est, by_index=True)

    lo, hi = max(est.timestamps[0], gt.timestamps[0]), min(est.timestamps[-1], gt.timestamps[-1])
    if lo - hi > max_diff:
        raise EvalError(
            f"no timestamps of {est_name} within {max_diff:g} s of {gt_name} (estimate spans "
            f"{est.timestamps[0]:.3f}..{est.timestamps[-1]:.3f}, ground truth {gt.timestamps[0]:.3f}..{gt.timestamps[-1]:.3f}); "
            "are both in seconds?"
        )
    try:
        gt_s, est_s = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=max_diff)
    except sync.SyncException:
        raise EvalError(
            f"no timestamps of {est_name} within {max_diff:g} s of {gt_name} although their time ranges overlap; "
            "are both sampled at the same instants (try a larger max_diff)?"
        ) from None
    _check_count(gt_s.num_poses, est_name, gt_name, f"within {max_diff:g} s")
    return Association(gt=from_evo(gt_s), est=from_evo(est_s), by_index=False)


def _check_count(n: int, est_name: str, gt_name: str, how: str) -> None:
    if n < MIN_MATCHES:
        raise EvalError(
            f"only {n} poses of {est_name} matched {gt_name} ({how}); need at least {MIN_MATCHES} to align and evaluate"
        )
