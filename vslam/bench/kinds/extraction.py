"""Kind ``extraction``: the learned presets' keypoint extraction against ORB in the same run, step by step, and
the guided matcher per call (``eval.extraction_speed``)."""

from __future__ import annotations

import time
from typing import Any

from vslam.bench.suite import BenchRow
from vslam.bench.tables import report_tables
from vslam.childproc import peak_rss_mb

# set name -> the preset whose slam.features are timed (its sequence, frames from the pose bench's validation start)
PRESETS = {"tum": ("tum_rgbd_learned", 100), "kitti": ("kitti_mono_learned", 80)}


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """``set``: frames (per sequence), repeats, threads, runtimes=[torch, onnxruntime], sets=[tum, kitti], detector
    (true: the shipped detector's mask step timed on the TUM frames too, and the learned front end's sum)."""
    import itertools

    from vslam.config import load_config
    from vslam.data.registry import open_sequence
    from vslam.eval.extraction_speed import SpeedSet, extraction_speed
    from vslam.paths import data_root
    from vslam.pipeline.config import PipelineConfig

    frames = int(overrides.get("frames", 20))
    sets = []
    for name in overrides.get("sets", list(PRESETS)):
        preset, first = PRESETS[str(name)]
        cfg = load_config(PipelineConfig, preset)
        seq = open_sequence(data_root() / cfg.dataset.path)
        images = [f.image for f in itertools.islice((f for f in seq if f.index >= first), frames)]
        extra = _detector_step() if overrides.get("detector", False) and name == "tum" else ()
        sets.append(SpeedSet(str(name), images, seq.calibration.cam0, cfg.slam.features, extra))
    t0 = time.perf_counter()
    res = extraction_speed(sets, repeats=int(overrides.get("repeats", 3)), threads=int(overrides.get("threads", 2)),
                           runtimes=tuple(str(r) for r in overrides.get("runtimes", ["torch", "onnxruntime"])))
    return {**res, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def _detector_step() -> tuple:
    """("detector", fn): the shipped detector's mask step as ``profiling.network_speed`` times it (detect, masks
    where the checkpoint has a mask head, the keypoints in the boxes), CPU, SLAM's score threshold."""
    from vslam.dynamic.config import DynamicConfig
    from vslam.dynamic.detector import default_weights, load_detector
    from vslam.dynamic.masking import in_boxes

    det = load_detector(default_weights(), conf=DynamicConfig().score_threshold, device="cpu")
    return (("detector", lambda im, xy: in_boxes(xy, det.detect(im).boxes, 4)),)


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Per row: ms per frame and x ORB of each extractor, ALIKE's steps and layers, guided matching per call."""
    from vslam.eval.extraction_speed import format_table

    return report_tables(rows, "## Keypoint extraction speed, learned presets vs ORB (`{name}`)", format_table)
