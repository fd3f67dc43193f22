"""ATE and RPE through evo's own metric objects, so the numbers equal ``evo_ape``/``evo_rpe``.

Everything here works on associated pairs (see ``associate``): alignment is
evo's Umeyama (``PosePath3D.align``), ATE is ``metrics.APE`` and RPE is
``metrics.RPE`` with consecutive (non-overlapping) pairs, evo's default; a
metres delta picks its pairs along the aligned estimate's path, as evo_rpe does.
Rotation angles are evo's definition (norm of scipy's rotation vector) computed
on whole arrays, because evo's per-pose loop takes seconds on KITTI-length runs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from evo import EvoException
from evo.core import metrics
from evo.core.metrics import PoseRelation, Unit
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from vslam.errors import EvalError
from vslam.eval.associate import Association, to_evo


@dataclass(frozen=True)
class ErrorStats:
    """Summary of one error array (unit given by the field that holds it); same definitions as evo."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    @classmethod
    def from_errors(cls, err: np.ndarray) -> ErrorStats:
        err = np.asarray(err, dtype=np.float64)
        return cls(
            rmse=float(np.sqrt(np.mean(err**2))),
            mean=float(np.mean(err)),
            median=float(np.median(err)),
            std=float(np.std(err)),
            min=float(np.min(err)),
            max=float(np.max(err)),
            n=int(err.size),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ErrorStats:
        return cls(**d)


@dataclass(frozen=True)
class Alignment:
    """est_aligned = s * R @ p_est + t (evo/Umeyama convention); identity for ``none``."""

    method: str
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) metres
    s: float

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "R": self.R.tolist(), "t": self.t.tolist(), "s": self.s}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Alignment:
        return cls(d["method"], np.asarray(d["R"], dtype=np.float64), np.asarray(d["t"], dtype=np.float64), float(d["s"]))


@dataclass(frozen=True)
class AteStats:
    """Absolute trajectory error after alignment: translation (m) and rotation angle (deg)."""

    translation: ErrorStats
    rotation_deg: ErrorStats

    def to_dict(self) -> dict[str, Any]:
        return {"translation_m": self.translation.to_dict(), "rotation_deg": self.rotation_deg.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AteStats:
        return cls(ErrorStats.from_dict(d["translation_m"]), ErrorStats.from_dict(d["rotation_deg"]))


@dataclass(frozen=True)
class RpeStats:
    """Relative pose error for one delta.

    delta/unit: as configured; frames: the frame delta used when unit is
    ``seconds`` (round(delta / median timestep)), else None.
    translation: metres per delta; rotation_deg: degrees per delta.
    """

    delta: float
    unit: str
    frames: int | None
    translation: ErrorStats
    rotation_deg: ErrorStats

    @property
    def label(self) -> str:
        unit = self.unit[:-1] if self.delta == 1 else self.unit  # "1 frame", "2 frames"
        extra = f" (= {self.frames} frames)" if self.frames is not None else ""
        return f"{self.delta:g} {unit}{extra}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "delta": self.delta,
            "unit": self.unit,
            "frames": self.frames,
            "translation_m": self.translation.to_dict(),
            "rotation_deg": self.rotation_deg.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RpeStats:
        return cls(
            d["delta"], d["unit"], d["frames"], ErrorStats.from_dict(d["translation_m"]), ErrorStats.from_dict(d["rotation_deg"])
        )


@dataclass
class RpeSeries:
    """Per-pair RPE values for plots: ``index`` is the associated pose index closing each pair."""

    index: np.ndarray
    translation: np.ndarray
    rotation_deg: np.ndarray


class DeltaNotApplicable(Exception):
    """An RPE delta the trajectory cannot serve (too short, no timestamps); becomes a note, not an error."""


def align(assoc: Association, method: str) -> tuple[Alignment, PoseTrajectory3D, PoseTrajectory3D]:
    """(alignment, GT as evo trajectory, aligned estimate as evo trajectory)."""
    gt = to_evo(assoc.gt, "ground truth")
    est = to_evo(assoc.est, "estimate")
    if method == "none":
        return Alignment("none", np.eye(3), np.zeros(3), 1.0), gt, est
    if method not in ("se3", "sim3"):
        raise EvalError(f"unknown alignment {method!r}; expected se3, sim3 or none")
    try:
        R, t, s = est.align(gt, correct_scale=(method == "sim3"))
    except EvoException as e:
        # Umeyama fails on degenerate point sets (all positions equal or collinear-rank-deficient).
        pos = np.asarray(est.positions_xyz)
        hint = ""
        if len(pos) and np.ptp(pos, axis=0).max() < 1e-9:  # a run that never initialised writes one pose throughout
            hint = f"; all {len(pos)} estimated positions are the same point (was any frame tracked? see stats.csv)"
        raise EvalError(f"cannot align the estimate to the ground truth ({method}): {e}{hint}") from None
    return Alignment(method, np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64), float(s)), gt, est


def ate(gt: PoseTrajectory3D, est_aligned: PoseTrajectory3D) -> tuple[AteStats, np.ndarray, np.ndarray]:
    """(stats, per-pose translation error (m), per-pose rotation error (deg))."""
    trans = metrics.APE(PoseRelation.translation_part)
    trans.process_data((gt, est_aligned))
    # evo's rotation_angle_deg is angle(inv(R_est) @ R_gt) pose by pose through
    # scipy; the same computation batched is far faster on long sequences (docs/speed.md).
    R_est = np.asarray(est_aligned.poses_se3)[:, :3, :3]
    R_gt = np.asarray(gt.poses_se3)[:, :3, :3]
    rot = rotation_angle_deg(np.swapaxes(R_est, 1, 2) @ R_gt)
    stats = AteStats(_stats(trans), ErrorStats.from_errors(rot))
    return stats, np.asarray(trans.error, dtype=np.float64), rot


def rpe(
    gt: PoseTrajectory3D,
    est_aligned: PoseTrajectory3D,
    delta: float,
    unit: str,
    *,
    seconds: bool = True,
) -> tuple[RpeStats, RpeSeries]:
    """RPE for one delta; raises DeltaNotApplicable when it yields no pair.

    seconds: whether the trajectories' timestamps are seconds (False for KITTI
    poses matched by line), needed for a ``seconds`` delta.
    """
    frames: int | None = None
    if unit == "seconds":
        if not seconds:
            raise DeltaNotApplicable(f"RPE delta {delta:g} s skipped: the poses have no timestamps")
        dt = float(np.median(np.diff(gt.timestamps))) if gt.num_poses > 1 else 0.0
        if not dt > 0:
            raise DeltaNotApplicable(f"RPE delta {delta:g} s skipped: cannot tell the timestep")
        frames = max(1, int(round(delta / dt)))
        evo_delta, evo_unit = float(frames), Unit.frames
    elif unit == "frames":
        evo_delta, evo_unit = float(delta), Unit.frames
    elif unit == "meters":
        evo_delta, evo_unit = float(delta), Unit.meters
    else:
        raise EvalError(f"unknown RPE delta unit {unit!r}; expected frames, meters or seconds")

    m = metrics.RPE(PoseRelation.translation_part, delta=evo_delta, delta_unit=evo_unit, all_pairs=False)
    try:
        m.process_data((gt, est_aligned))
    except EvoException:
        span = f"{gt.path_length:.2f} m" if unit == "meters" else f"{gt.num_poses} poses"
        raise DeltaNotApplicable(f"RPE delta {delta:g} {unit} skipped: the trajectory is too short ({span})") from None
    # m.E holds the full relative error poses; their angles are evo's
    # rotation_angle_deg RPE, computed batched instead of pose by pose.
    rot = rotation_angle_deg(np.asarray(m.E)[:, :3, :3])
    stats = RpeStats(delta, unit, frames, _stats(m), ErrorStats.from_errors(rot))
    series = RpeSeries(np.asarray(m.delta_ids, dtype=np.int64), np.asarray(m.error, dtype=np.float64), rot)
    return stats, series


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """(N,3,3) rotations -> (N,) angles in degrees, as evo's ``so3_log_angle`` (scipy rotvec norm)."""
    return np.degrees(Rotation.from_matrix(R).magnitude())


def _stats(m: metrics.PE) -> ErrorStats:
    # evo's own statistics, so the comparison with the CLI is exact.
    s = m.get_all_statistics()
    return ErrorStats(
        rmse=float(s["rmse"]),
        mean=float(s["mean"]),
        median=float(s["median"]),
        std=float(s["std"]),
        min=float(s["min"]),
        max=float(s["max"]),
        n=int(len(m.error)),
    )
