"""Kind ``detector_speed``: detectors side by side, ms per frame of ``detect()`` (letterbox, network, NMS and,
where the checkpoint has a mask head, its masks in the image's pixels) on TUM teddy frames with composited walkers
(validation walker seed by default) or on labelled photos resized to 640x480, as SLAM runs them (its score
threshold, torch on the CPU).

The models run in turn on each frame, so a load that comes and goes on a shared machine reaches them alike; read
the ratio between them beside the absolute times."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from vslam.bench.suite import BenchRow
from vslam.bench.tables import report_tables
from vslam.errors import ConfigError


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """``set``: models=[checkpoint, ...] (paths from the repository root), frames (30), threads (2), seed (walker
    seed of the composite, 1), start (first frame, 10), or photos (folder:split of labelled photos instead, resized
    to 640x480) -> {"models": {path: {"ms_median", "ms_min",
    "detections", "masks"}} keyed by the file's stem, "frames", "threads"}."""
    import torch

    from vslam.data.composite import MakeDynamicConfig, composited_frames
    from vslam.dynamic.config import DynamicConfig
    from vslam.dynamic.detector import load_detector
    from vslam.paths import data_root

    models = [str(m) for m in overrides.get("models", ())]
    if not models or len({Path(m).stem for m in models}) != len(models):
        raise ConfigError("bench kind detector_speed needs set: models=[file, ...] (files of distinct names)")
    n, threads = int(overrides.get("frames", 30)), int(overrides.get("threads", 2))
    torch.set_num_threads(threads)
    if overrides.get("photos"):  # labelled photos (folder:split under $VSLAM_DATA), each resized to 640x480
        import cv2

        from vslam.train.photos import load_records

        folder, _, split = str(overrides["photos"]).partition(":")
        _, records = load_records(data_root() / folder, split or "val")  # type: ignore[arg-type]
        frames = [cv2.resize(r.image(), (640, 480), interpolation=cv2.INTER_AREA) for r in records[:n]]
    else:
        start = int(overrides.get("start", 10))
        cfg = MakeDynamicConfig(n_people=3, seed=int(overrides.get("seed", 1)), max_frames=start + n)
        frames = [img for _, img, _, _, _ in composited_frames(data_root() / "tum" / "rgbd_dataset_freiburg3_teddy",
                                                               data_root() / "coco128", cfg, start=start)]
    dets = [load_detector(m, conf=DynamicConfig().score_threshold, field="models") for m in models]
    for d in dets:  # warm-up: first-call allocations and kernel choices
        for img in frames[:3]:
            d.detect(img)
    times: list[list[float]] = [[] for _ in dets]
    counts: list[list[int]] = [[] for _ in dets]
    masked = [False] * len(dets)
    for img in frames:
        for k, d in enumerate(dets):
            t0 = time.perf_counter()
            out = d.detect(img)
            times[k].append(1e3 * (time.perf_counter() - t0))
            counts[k].append(len(out.boxes))
            masked[k] = masked[k] or out.masks is not None
    res = {Path(m).stem: {"ms_median": float(np.median(t)), "ms_min": float(np.min(t)), "detections": float(np.mean(c)),
               "masks": masked[k]} for k, (m, t, c) in enumerate(zip(models, times, counts))}
    return {"models": res, "frames": len(frames), "threads": threads, "shape": list(frames[0].shape[:2])}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    def one(r: dict[str, Any]) -> list[str]:
        h, w = r["shape"]
        out = [f"{r['frames']} frames of {w}x{h}, {r['threads']} torch threads, models in turn on each frame", "",
               "| model | median ms | min ms | detections / frame | masks | ratio to the first |", "|---|---|---|---|---|---|"]
        first = next(iter(r["models"].values()))["ms_median"]
        for name, m in r["models"].items():
            out.append(f"| {name} | {m['ms_median']:.1f} | {m['ms_min']:.1f} | {m['detections']:.1f} | "
                       f"{'yes' if m['masks'] else 'no'} | {m['ms_median'] / first:.2f} |")
        return out

    return report_tables(rows, "## Detector speed (`{name}`)", one)
