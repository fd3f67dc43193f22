"""``vslam run --profile``: where each frame's time goes, stage by stage, and the peak memory (docs/speed.md).

Read back from the run's ``stats.csv``, so a profile costs the run nothing extra and any finished run can be
profiled again (``python -m vslam.profiling runs/x/stats.csv``). Per stage: the mean ms per frame (a stage that
runs on keyframes only, such as local BA, counts 0 on the other frames, so the means add up to the frame
time), the median over the frames it ran on, how many frames that was, and its share of the mean total.
"decode" is the time tracking waited for the next frame (frames are read ahead, beside tracking). With
``runtime.frontend_thread`` (the default) the image-only stages (features, lines, the dynamic-object detector and,
without dynamic filtering, depth) are computed there too -- in a child process with ``runtime.frontend_process``
(the default), else on a thread: their rows are then their cost there, on the second core, and not part of
"total" (the tracking call); "decode" includes any wait for them (and, for the first frame, the child's start).
"""

from __future__ import annotations

import csv
import itertools
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from vslam.childproc import peak_rss_mb

#: pipeline order; sub-stages of mapping are indented in the table
ORDER = ("decode", "features", "detector", "dynamic", "lines", "depth", "pose", "mapping", "map_create",
         "map_fuse_cull", "map_ba", "map_wait", "map_loop", "total")


def profile(stats_csv: str | Path) -> dict[str, Any]:
    """-> {"frames": N, "stages": {stage: {"mean_ms", "median_ms", "frames", "share"}}, "peak_rss_mb": this
    process and its largest child}."""
    with open(stats_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    cols = [c[3:] for c in (rows[0] if rows else {}) if c.startswith("ms_")]
    stages: dict[str, dict[str, float]] = {}
    for col in sorted(cols, key=lambda c: ORDER.index(c) if c in ORDER else len(ORDER)):
        ran = [float(r["ms_" + col]) for r in rows if r.get("ms_" + col, "") not in ("", None)]
        if not ran:
            continue
        stages[col] = {"mean_ms": sum(ran) / len(rows), "median_ms": statistics.median(ran), "frames": len(ran)}
    total = stages.get("total", {}).get("mean_ms", 0.0)
    for st in stages.values():
        st["share"] = st["mean_ms"] / total if total > 0 else float("nan")
    # the frame rate counts the waits for frames too: with the front-end thread, the time tracking waited for
    # features ("decode") is outside "total" but not outside the run
    wall = total + stages.get("decode", {}).get("mean_ms", 0.0)
    return {"frames": len(rows), "stages": stages, "wall_ms_per_frame": wall,
            "peak_rss_mb": peak_rss_mb()}


def format_profile(p: dict[str, Any]) -> str:
    """A fixed-width table of ``profile``'s result."""
    lines = [f"{'stage':<16}{'mean ms/frame':>14}{'median ms':>11}{'frames':>8}{'share':>8}"]
    for name, st in p["stages"].items():
        label = ("  " + name[4:]) if name.startswith("map_") else name
        lines.append(f"{label:<16}{st['mean_ms']:>14.1f}{st['median_ms']:>11.1f}{st['frames']:>8d}{100 * st['share']:>7.0f}%")
    wall = p.get("wall_ms_per_frame")
    fps = f", {1e3 / wall:.1f} frames/s (tracking + waiting for frames)" if wall else ""
    lines.append(f"{p['frames']} frames{fps}, peak RSS {p['peak_rss_mb']:.0f} MB")
    return "\n".join(lines)


def write_profile(stats_csv: str | Path, out: str | Path) -> dict[str, Any]:
    p = profile(stats_csv)
    from vslam.outputs import write_text

    write_text(out, json.dumps(p, indent=1) + "\n")
    return p


def line_ba_cost(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Point + line features: the back-end cost of lines. A SLAM run with lines (``config`` + ``overrides``) in which
    every local BA that has lines is solved twice on the same window, first without its lines (its result
    discarded), then with them; CPU time of the solving thread (``time.thread_time``: the front-end thread's work
    is not counted). Two separate runs would compare different windows, keyframes and machine load; this compares
    like with like. -> {bas, points_ms, lines_ms (means per BA), ratio (sum with / sum without), ate_rmse}."""
    import dataclasses

    import vslam.mapping.local_mapping as local_mapping
    from vslam.config import deep_merge
    from vslam.pipeline import Pipeline, PipelineConfig

    solve = local_mapping.local_bundle_adjustment
    cpu: dict[str, list[float]] = {"points": [], "lines": []}

    def both(problem, camera, cfg, cache=None):
        # the factor cache is left out: both solves then build their factors, as the comparison needs
        if problem.lines is None:
            return solve(problem, camera, cfg)
        t = time.thread_time()
        solve(dataclasses.replace(problem, lines=None), camera, cfg)
        cpu["points"].append(time.thread_time() - t)
        t = time.thread_time()
        res = solve(problem, camera, cfg)
        cpu["lines"].append(time.thread_time() - t)
        return res

    cfg = PipelineConfig.load(config, deep_merge(overrides, {"output": {"dir": out_dir},
                                                             "slam": {"lines": {"enabled": True}}}))
    local_mapping.local_bundle_adjustment = both  # this job's own process: the pipeline's BA calls go through it
    try:
        res = Pipeline(cfg).run()
    finally:
        local_mapping.local_bundle_adjustment = solve
    p, q = 1e3 * np.array(cpu["points"]), 1e3 * np.array(cpu["lines"])
    return {"bas": len(p), "points_ms": float(p.mean()) if len(p) else None, "lines_ms": float(q.mean()) if len(q) else None,
            "ratio": float(q.sum() / p.sum()) if len(p) and p.sum() > 0 else None,
            "ate_rmse": None if res.eval is None else res.eval.ate.translation.rmse}


def network_speed(device: str = "auto", frames: int = 20, repeats: int = 3, threads: int = 2,
                  sequence: str = "tum/rgbd_dataset_freiburg3_teddy", n_features: int = 1500) -> dict[str, Any]:
    """ms per 640x480 frame of the learned front end, stage by stage, on ``device`` (auto: CUDA when torch sees
    a GPU): ConvPoint keypoints (int8 on the CPU, float on CUDA; ``n_features`` as the SLAM configs), the shipped
    detector's mask step (detect + keypoints in boxes), LSD lines (always the CPU) and VLADNet (once per
    keyframe). "front_end" is one frame through the first three as ``SlamTracker.frontend`` runs them: in a row on
    the CPU, LSD on a thread beside the networks on CUDA (``RuntimeConfig.lines_beside_networks``).
    Medians over ``frames`` frames of ``sequence`` x ``repeats`` after a warm-up; torch and OpenCV get
    ``threads`` CPU threads (the project's 2-core target). Needs torch, numpy and cv2 only, so it runs on a
    machine without the SLAM back end (the GPU machine)."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2
    import torch

    from vslam.data.tum import TumRgbdSequence
    from vslam.nn.device import pick_device
    from vslam.dynamic.config import DynamicConfig
    from vslam.dynamic.detector import default_weights, load_detector
    from vslam.dynamic.masking import in_boxes
    from vslam.features.base import FeatureConfig
    from vslam.features.convpoint import ConvPointExtractor
    from vslam.features.lines import LineExtractor
    from vslam.loop.descriptor import default_vladnet_path
    from vslam.loop.vladnet import VladNetDescriptor
    from vslam.paths import data_root

    dev = pick_device(device, "speed.device")
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    seq = TumRgbdSequence(data_root() / sequence, sensor="mono")
    cam = seq.calibration.cam0
    images = [f.image for f in itertools.islice(seq, frames)]
    conv = ConvPointExtractor(FeatureConfig(extractor="convpoint", n_features=n_features, device=dev.type))
    det = load_detector(default_weights(), conf=DynamicConfig().score_threshold, device=dev)  # as SLAM runs it
    lsd = LineExtractor()
    vlad = VladNetDescriptor.from_file(default_vladnet_path(), device=dev.type)

    def mask_step(im: np.ndarray) -> None:
        in_boxes(conv_uv, det.detect(im).boxes, 4)

    pool = ThreadPoolExecutor(1) if dev.type == "cuda" else None  # RuntimeConfig.lines_beside_networks' default

    def front_end(im: np.ndarray) -> None:
        pending = pool.submit(lsd.detect, im, cam) if pool is not None else None
        conv.detect(im, cam)
        mask_step(im)
        pending.result() if pending is not None else lsd.detect(im, cam)

    conv_uv = conv.detect(images[0], cam).raw
    stages = {"convpoint": lambda im: conv.detect(im, cam), "detector": mask_step,
              "lines": lambda im: lsd.detect(im, cam), "vladnet": vlad.describe, "front_end": front_end}
    out: dict[str, Any] = {}
    for name, fn in stages.items():
        for im in images[:3]:  # warm-up: allocations, kernel selection, cuDNN autotuning
            fn(im)
        ms = []
        for _ in range(repeats):
            for im in images:
                t0 = time.perf_counter()
                fn(im)
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                ms.append((time.perf_counter() - t0) * 1e3)
        out[name] = statistics.median(ms)
    if pool is not None:
        pool.shutdown()
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"CPU, {threads} threads"
    return {"device": dev.type, "device_name": name, "torch": torch.__version__, "frames": len(images),
            "repeats": repeats, "ms": out,
            "peak_gpu_mb": torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else None}


def format_speed(rows: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """Markdown: one line per measured device."""
    cols = ("convpoint", "detector", "lines", "vladnet", "front_end")
    lines = ["| row | device | " + " | ".join(cols) + " | peak GPU memory |", "|---|---|" + "---|" * (len(cols) + 1)]
    for name, r in rows:
        mem = "–" if r.get("peak_gpu_mb") is None else f"{r['peak_gpu_mb']:.0f} MB"
        lines.append(f"| {name} | {r['device_name']} (torch {r['torch']}) | " +
                     " | ".join(f"{r['ms'][c]:.1f}" for c in cols) + f" | {mem} |")
    return lines


if __name__ == "__main__":  # profile a finished run: python -m vslam.profiling runs/x/stats.csv
    print(format_profile(profile(sys.argv[1])))
