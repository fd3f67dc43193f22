"""A run's config: the sequence (``DatasetConfig``, from ``vslam.data.config``), which tracker and its settings,
evaluation and outputs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from vslam.config import load_config
from vslam.data.config import DatasetConfig
from vslam.eval import EvalConfig
from vslam.runtime import RuntimeConfig
from vslam.tracking.baseline import OdometryConfig
from vslam.tracking.slam import SlamConfig
from vslam.viz.rerun_log import ViewerConfig


@dataclass(frozen=True)
class OutputConfig:
    dir: str = "runs/latest"
    formats: tuple[str, ...] = ("tum", "kitti")
    report: bool = True
    # maps that were never merged into the one with most frames: kept in trajectory_final.tum.txt (each in its
    # own frame; stats.csv says which) or dropped from it
    unmerged: Literal["keep", "drop"] = "keep"
    viewer: ViewerConfig = ViewerConfig()  # stream the run to Rerun (vslam.viz.rerun_log, docs/viewer.md); off


@dataclass(frozen=True)
class PipelineConfig:
    dataset: DatasetConfig = DatasetConfig()
    tracker: Literal["baseline", "slam"] = "slam"  # baseline: frame-to-frame odometry; slam: map + local BA
    odometry: OdometryConfig = OdometryConfig()  # settings of the baseline tracker
    slam: SlamConfig = SlamConfig()  # settings of the SLAM tracker
    runtime: RuntimeConfig = RuntimeConfig()  # threads, front-end process: how fast, never what is computed
    eval: EvalConfig = EvalConfig()
    output: OutputConfig = OutputConfig()

    @staticmethod
    def load(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> PipelineConfig:
        return load_config(PipelineConfig, path, overrides, nonnegative=True)
