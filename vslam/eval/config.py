"""Configuration of a trajectory evaluation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from vslam.errors import ConfigError

Align = Literal["se3", "sim3", "none", "auto"]
DeltaUnit = Literal["frames", "meters", "seconds"]
ALIGNS: tuple[str, ...] = ("se3", "sim3", "none", "auto")
DELTA_UNITS: tuple[str, ...] = ("frames", "meters", "seconds")


@dataclass(frozen=True)
class EvalConfig:
    """How to compare an estimated trajectory with ground truth.

    align: Umeyama alignment of the estimate to GT before ATE/RPE. ``auto`` is
        ``sim3`` for monocular runs (scale is unobservable, so the usual
        literature protocol recovers it) and ``se3`` otherwise.
    max_diff: seconds; largest timestamp difference for associating poses.
    rpe_deltas: (value, unit) pairs, unit in frames/meters/seconds. A seconds
        delta becomes ``round(value / median timestep)`` frames (at least 1)
        of the associated poses, because evo only knows frames and meters.
        A delta the trajectory is too short for is dropped with a note.
    kitti_lengths: metres; segment lengths of the KITTI odometry metric.
    kitti_step: frames between segment start frames (10 = 1 s at KITTI's 10 Hz).
    plots: whether ``write_report`` draws PNGs.
    enabled: ``vslam run`` reads and evaluates the sequence's ground truth (``--no-eval``: off).
    """

    align: Align = "auto"
    max_diff: float = 0.02
    rpe_deltas: tuple[tuple[float, str], ...] = ((1, "frames"), (1.0, "meters"), (1.0, "seconds"))
    kitti_lengths: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
    kitti_step: int = 10
    plots: bool = True
    enabled: bool = True

    def __post_init__(self) -> None:
        if self.align not in ALIGNS:
            raise ConfigError(f"eval.align must be one of {', '.join(ALIGNS)}, got {self.align!r}")
        if not self.max_diff > 0:
            raise ConfigError(f"eval.max_diff must be > 0 seconds, got {self.max_diff!r}")
        deltas = []
        for d in self.rpe_deltas:
            if not isinstance(d, (tuple, list)) or len(d) != 2:
                raise ConfigError(f"eval.rpe_deltas entries must be (value, unit) pairs, got {d!r}")
            value, unit = d
            if unit not in DELTA_UNITS:
                raise ConfigError(f"eval.rpe_deltas unit must be one of {', '.join(DELTA_UNITS)}, got {unit!r}")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ConfigError(f"eval.rpe_deltas value must be a positive number, got {value!r}")
            if unit == "frames" and float(value) != int(value):
                raise ConfigError(f"eval.rpe_deltas frame delta must be a whole number, got {value!r}")
            deltas.append((int(value) if unit == "frames" else float(value), str(unit)))
        object.__setattr__(self, "rpe_deltas", tuple(deltas))
        if not self.kitti_lengths or any(not L > 0 for L in self.kitti_lengths):
            raise ConfigError(f"eval.kitti_lengths must be positive metres, got {self.kitti_lengths!r}")
        object.__setattr__(self, "kitti_lengths", tuple(float(L) for L in self.kitti_lengths))
        if isinstance(self.kitti_step, bool) or not isinstance(self.kitti_step, int) or self.kitti_step < 1:
            raise ConfigError(f"eval.kitti_step must be a positive whole number of frames, got {self.kitti_step!r}")

    def resolve_align(self, monocular: bool) -> Literal["se3", "sim3", "none"]:
        """The alignment actually used: ``auto`` -> sim3 for monocular runs, else se3."""
        if self.align == "auto":
            return "sim3" if monocular else "se3"
        return self.align  # type: ignore[return-value]

    def to_dict(self) -> dict[str, object]:
        return {
            "align": self.align,
            "max_diff": self.max_diff,
            "rpe_deltas": [[v, u] for v, u in self.rpe_deltas],
            "kitti_lengths": list(self.kitti_lengths),
            "kitti_step": self.kitti_step,
            "plots": self.plots,
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> EvalConfig:
        kw = dict(d)
        if "rpe_deltas" in kw:
            kw["rpe_deltas"] = tuple(tuple(x) for x in kw["rpe_deltas"])  # type: ignore[union-attr]
        if "kitti_lengths" in kw:
            kw["kitti_lengths"] = tuple(kw["kitti_lengths"])  # type: ignore[arg-type]
        return cls(**kw)  # type: ignore[arg-type]
