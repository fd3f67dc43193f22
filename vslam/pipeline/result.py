"""What a run gives back: ``RunResult`` (trajectory, per-frame stats, evaluation, paths, the run in numbers)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vslam.data.trajectory import Trajectory
from vslam.errors import VslamError
from vslam.eval import EvalResult


@dataclass
class RunResult:
    trajectory: Trajectory
    tracked: np.ndarray  # (N,) bool: measured (True) or predicted through a failure (False)
    stats: list[dict[str, float]]
    eval: EvalResult | None
    paths: dict[str, Path]
    seconds: float
    # A problem found once the trajectory was written (ground truth unusable, no frame tracked): the run's
    # outputs stand, and ``vslam run`` reports it as an error after them.
    error: VslamError | None = None
    # the final map of each written pose, and the evaluation of each map when there are several
    map_ids: np.ndarray | None = None
    map_evals: dict[int, EvalResult] = field(default_factory=dict)
    eval_groundtruth: Trajectory | None = None  # what ``eval`` was measured against
    dropped: int | None = None  # live input: frames its queue dropped (stats.csv ``dropped``); None: recorded input
    # the trajectory is in metres (depth, stereo, an IMU-scaled monocular map); False: scored with Sim3
    metric_scale: bool = True
    # the map ``eval`` scores when maps were never merged (the one with most poses); None: the whole run
    scored_map: int | None = None
    # why ground truth was found but not used (too few poses to align), for the summary
    eval_skipped: str = ""
    # indices of the frames the reader could not decode (skipped with a warning; no stats.csv row)
    skipped: list[int] = field(default_factory=list)
    # how the reader paired rgb with depth / left with right over the recording (None: nothing to pair)
    association: Any = None
    # recovery counts of the tracker (``Odometry.recovery_stats``: new maps, merges, map switches)
    recovery: dict[str, int] = field(default_factory=dict)

    @property
    def fps(self) -> float:
        return len(self.trajectory) / self.seconds if self.seconds > 0 else float("nan")

    @property
    def n_frames(self) -> int:
        """Frames the run read (a row each in stats.csv), posed or not."""
        return len(self.stats)

    def maps_summary(self) -> list[dict[str, Any]]:
        """One entry per final map, largest first: id, poses, and its own ATE when it was scored."""
        ids = self.map_ids if self.map_ids is not None else np.zeros(len(self.trajectory), np.int64)
        maps, counts = np.unique(ids, return_counts=True)
        out = []
        for m, n in sorted(zip(maps.tolist(), counts.tolist()), key=lambda mn: (-mn[1], mn[0])):
            e = self.map_evals.get(m) if self.map_evals else (self.eval if len(maps) == 1 else None)
            entry: dict[str, Any] = {"map": int(m), "poses": int(n), "tracked": int(np.sum(self.tracked[ids == m]))}
            if e is not None:
                entry.update(ate_rmse=e.ate.translation.rmse, align=e.alignment.method, scale=e.alignment.s,
                             matched=e.n_matched)
            out.append(entry)
        return out

    def run_summary(self) -> dict[str, Any]:
        """The whole run in numbers (``metrics.json`` ``run``): frames read, posed, tracked, the maps, and what
        the headline ATE scores."""
        n, posed = self.n_frames, len(self.trajectory)
        return {"frames": n, "skipped": len(self.skipped), "posed": posed, "posed_fraction": posed / n if n else 0.0,
                "tracked": int(self.tracked.sum()), "metric_scale": self.metric_scale,
                "scored": "whole run" if self.scored_map is None else f"largest map ({self.scored_map})",
                "scored_map": self.scored_map, "maps": self.maps_summary(), **self.recovery,
                "association": dataclasses.asdict(self.association) if self.association is not None else None}
