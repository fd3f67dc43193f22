"""The outcome of one evaluation: numbers for JSON, arrays for plots."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vslam.eval.config import EvalConfig
from vslam.eval.kitti import KittiOdometryError
from vslam.eval.metrics import Alignment, AteStats, RpeSeries, RpeStats

SCHEMA = "vslam.eval/1"


@dataclass
class EvalArrays:
    """Per-pose data of the associated pairs, for plots only (never written to JSON).

    t: (N,) GT timestamps (seconds, or line indices when ``time_unit`` is "frame").
    gt_xyz, est_xyz: (N,3) metres; est_xyz after alignment.
    ate_t: (N,) metres; ate_r: (N,) degrees.
    rpe: per RPE label (see ``RpeStats.label``), the per-pair series.
    """

    t: np.ndarray
    gt_xyz: np.ndarray
    est_xyz: np.ndarray
    ate_t: np.ndarray
    ate_r: np.ndarray
    rpe: dict[str, RpeSeries] = field(default_factory=dict)


@dataclass
class EvalResult:
    """Everything one evaluation produced.

    time_unit: "s", or "frame" when KITTI poses without times were matched by line.
    n_est, n_gt: poses in the inputs; n_matched: associated pairs.
    gt_length_m / est_length_m: path lengths over the matched poses (estimate after
    alignment, so in GT units). duration: last - first matched GT time (time_unit).
    kitti: the devkit metric, or None with ``kitti_reason``.
    notes: things a reader must know (dropped deltas, matching mode).
    arrays: per-pose data for plots; None after ``from_dict``.
    """

    config: EvalConfig
    est_path: str | None
    gt_path: str | None
    monocular: bool
    alignment: Alignment
    ate: AteStats
    rpe: list[RpeStats]
    kitti: KittiOdometryError | None
    kitti_reason: str | None
    n_est: int
    n_gt: int
    n_matched: int
    matched_by: str
    time_unit: str
    duration: float
    gt_length_m: float
    est_length_m: float
    notes: list[str] = field(default_factory=list)
    # an SE3-scored (metric) run's Sim3 scale, and a warning when it is far from 1 (a wrong unit)
    scale_fit: float | None = None
    scale_warning: str = ""
    arrays: EvalArrays | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (plain floats, lists); the per-pose arrays are left out."""
        return {
            "schema": SCHEMA,
            "config": self.config.to_dict(),
            "est_path": self.est_path,
            "gt_path": self.gt_path,
            "monocular": self.monocular,
            "alignment": self.alignment.to_dict(),
            "ate": self.ate.to_dict(),
            "rpe": [r.to_dict() for r in self.rpe],
            "kitti": self.kitti.to_dict() if self.kitti is not None else None,
            "kitti_reason": self.kitti_reason,
            "n_est": self.n_est,
            "n_gt": self.n_gt,
            "n_matched": self.n_matched,
            "matched_by": self.matched_by,
            "time_unit": self.time_unit,
            "duration": self.duration,
            "gt_length_m": self.gt_length_m,
            "est_length_m": self.est_length_m,
            "notes": list(self.notes),
            "scale_fit": self.scale_fit,
            "scale_warning": self.scale_warning,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EvalResult:
        """Inverse of ``to_dict`` (e.g. a metrics.json read back); ``arrays`` is None."""
        if d.get("schema") != SCHEMA:
            raise ValueError(f"not a {SCHEMA} result (schema {d.get('schema')!r})")
        return cls(
            config=EvalConfig.from_dict(d["config"]),
            est_path=d["est_path"],
            gt_path=d["gt_path"],
            monocular=d["monocular"],
            alignment=Alignment.from_dict(d["alignment"]),
            ate=AteStats.from_dict(d["ate"]),
            rpe=[RpeStats.from_dict(r) for r in d["rpe"]],
            kitti=KittiOdometryError.from_dict(d["kitti"]) if d["kitti"] is not None else None,
            kitti_reason=d["kitti_reason"],
            n_est=d["n_est"],
            n_gt=d["n_gt"],
            n_matched=d["n_matched"],
            matched_by=d["matched_by"],
            time_unit=d["time_unit"],
            duration=d["duration"],
            gt_length_m=d["gt_length_m"],
            est_length_m=d["est_length_m"],
            notes=list(d["notes"]),
            scale_fit=d.get("scale_fit"),
            scale_warning=d.get("scale_warning", ""),
        )

    def ate_text(self) -> str:
        """``ATE 0.0039 m rmse (se3)``: the number with the alignment that made it (and Sim3's scale)."""
        s = f"ATE {self.ate.translation.rmse:.4f} m rmse ({self.alignment.method}"
        return s + (f", scale {self.alignment.s:.4f})" if self.alignment.method == "sim3" else ")")

    def summary(self) -> str:
        """One line for logs and CLIs."""
        s = self.ate_text() + f", {self.n_matched} poses"
        if self.kitti is not None:
            s += f", KITTI t_rel {self.kitti.t_rel:.2f} % r_rel {self.kitti.r_rel:.3f} deg/100m"
        return s
