"""Kinds ``features`` (the homography benchmark) and ``pose`` (two-view pose AUC) of keypoint methods."""

from __future__ import annotations

import time
from typing import Any

from vslam.bench.suite import BenchRow
from vslam.bench.tables import report_tables
from vslam.childproc import peak_rss_mb


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Learned keypoints: ConvPoint vs ORB vs SIFT on the same held-out pairs (``set``: keypoints, pairs, images, seed,
    weights=<file>; ``eval.keypoints``)."""
    import torch

    from vslam.eval.keypoints import FeatureBenchConfig, run_feature_bench
    from vslam.features.convpoint import default_weights
    from vslam.paths import data_root

    torch.set_num_threads(2)
    t0 = time.perf_counter()
    cfg = FeatureBenchConfig(n_keypoints=int(overrides.get("keypoints", 1000)), pairs_per_image=int(overrides.get("pairs", 2)),
                             max_images_per_source=int(overrides.get("images", 12)), seed=int(overrides.get("seed", 0)))
    res = run_feature_bench(str(overrides.get("weights") or default_weights()), data_root(), cfg)
    return {**res, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Learned keypoints: the homography benchmark and epipolar inliers, ConvPoint vs ORB vs SIFT in one run."""
    from vslam.eval.keypoints import format_table

    return report_tables(rows, "## Keypoints: ConvPoint vs ORB vs SIFT (`{name}`)", format_table)


def job_pose(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Two-view relative pose AUC of keypoint methods on real pairs with ground truth (``set``: methods=[names],
    keypoints, pairs, threads; ``eval.pose_auc``)."""
    import torch

    from vslam.eval.pose_auc import PoseBenchConfig, pose_benchmark, standard_methods
    from vslam.paths import data_root

    threads = int(overrides.get("threads", 2))
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    cfg = PoseBenchConfig(n_keypoints=int(overrides.get("keypoints", 2000)), pairs=int(overrides.get("pairs", 50)))
    names = tuple(str(m) for m in overrides.get("methods", ["orb", "sift", "alike-t"]))
    res = pose_benchmark(standard_methods(cfg.n_keypoints, names), data_root(), cfg)
    return {**res, "threads": threads, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def pose_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Two-view pose AUC at 5/10/20 degrees per pair set and extraction ms per frame, methods of one run."""
    from vslam.eval.pose_auc import format_table

    return report_tables(rows, "## Keypoints: two-view pose AUC (`{name}`)", format_table)
