"""Optional SLAM stages behind one interface (``Stage``); ``build_stages`` makes the enabled ones, in the order
their hooks run."""

from __future__ import annotations

from typing import Any

from vslam.tracking.stages.base import Stage


def build_stages(slam: Any, detector: object | None = None) -> list[Stage]:
    """The stages ``slam.cfg`` enables. The order is the order of every hook: loop closing first (a lost frame is
    relocalised by place recognition before the other stages measure it), the IMU (it takes the frame's
    samples and predicts), then dynamic filtering (it decides which keypoints the others see), lines (they refine
    a tracked pose), dense depth tracking (the last recovery step). ``detector``: see ``SlamTracker``."""
    cfg, stages = slam.cfg, []
    if cfg.loop.enabled or cfg.load_map:
        from vslam.loop.closing import LoopCloser
        from vslam.tracking.stages.loop import LoopStage

        loop = LoopCloser(slam.map, slam.cam, slam.stereo_cam, slam.sensor, cfg.loop, cfg.backend, slam.mapper)
        loop.frames = slam.frames
        stages.append(LoopStage(loop, cfg.loop.relocalise))
    if cfg.inertial.enabled:
        from vslam.tracking.stages.inertial import InertialStage
        from vslam.tracking.vio import Vio

        stages.append(InertialStage(Vio(slam.calib, slam.sensor, cfg.inertial, slam.map)))
    if cfg.dynamic.enabled:
        from vslam.dynamic import DynamicFilter
        from vslam.tracking.stages.dynamic import DynamicStage

        stages.append(DynamicStage(DynamicFilter(cfg.dynamic, slam.cam, detector)))
    if cfg.lines.enabled:
        from vslam.tracking.stages.lines import LineStage

        beside = slam.runtime.lines_beside_networks
        if beside is None:
            beside = getattr(getattr(slam.extractor, "device", None), "type", "cpu") == "cuda"
        stages.append(LineStage(slam, beside))
    if slam.sensor == "rgbd" and cfg.dense.enabled:
        from vslam.tracking.dense import DenseOdometry
        from vslam.tracking.stages.dense import DenseStage

        stages.append(DenseStage(DenseOdometry(slam.cam, cfg.dense)))
    return stages


__all__ = ["Stage", "build_stages"]
