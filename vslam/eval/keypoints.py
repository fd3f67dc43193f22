"""``vslam eval-features``: ConvPoint against ORB and SIFT on the same pairs (learned keypoints, "Evaluation").

Homography benchmark (SuperPoint §7 / HPatches protocol): every held-out real image (COCO128 from
``coco_split``, TUM teddy / KITTI 07 / EuRoC V1_01 frames from their splits -- never trained on) is warped by
``pairs_per_image`` random homographies; each pair is scored twice, as ``viewpoint`` (the warp alone) and
``illumination`` (the warp plus ``homography.illumination_change`` on the warped side). Per method, the
``n_keypoints`` best keypoints of each side, matched by mutual nearest neighbour (no ratio test: the
protocol scores the descriptor, not a filter):

* repeatability: share of keypoints (seen by both images) with a keypoint of the other side within 3 px;
* localization error: mean pixel distance of those repeated pairs;
* matching score: correct matches (<= 3 px) over the keypoints seen by both images;
* MMA@1/3/5: share of the matches within 1/3/5 px of the true warp;
* homography accuracy @1/3/5: share of pairs whose RANSAC homography (OpenCV, 3 px) maps the image corners
  within 1/3/5 px (mean) of the truth.

Consecutive real frames with ground-truth poses (``epipolar``): TUM teddy and KITTI 07 held-out frames paired
``gap`` apart, mutual nearest neighbours with a ratio test of 0.9; inlier ratio = share of matches whose
symmetric epipolar distance to the ground-truth essential matrix is under 1 px (undistorted pixels).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from vslam.features.matching import match_mutual
from vslam.geometry.triangulation import fundamental
from vslam.progress import Progress

log = logging.getLogger(__name__)

# a method: grey image -> (xy (N,2) float64, desc (N,D) uint8 or float32)
Method = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class FeatureBenchConfig:
    n_keypoints: int = 1000
    pairs_per_image: int = 2
    seed: int = 0
    max_images_per_source: int = 12  # evenly spaced over the held-out part of each source
    eps_px: float = 3.0
    gap: dict | None = None  # epipolar pairs: frames apart per sequence (default tum 5, kitti 2)


def held_out_images(root: Path, max_per_source: int) -> dict[str, list[tuple[str, np.ndarray]]]:
    """Grey held-out images per source, the splits of ``keypoint_data.KeypointSplits``."""
    from vslam.train.keypoint_data import KeypointSplits, image_files

    files = image_files(KeypointSplits(), root, held_out=True)
    out = {}
    for name, fs in files.items():
        pick = np.unique(np.linspace(0, len(fs) - 1, min(max_per_source, len(fs))).round().astype(int)) if fs else []
        ims = [(fs[i].name, cv2.imread(str(fs[i]), cv2.IMREAD_GRAYSCALE)) for i in pick]
        out[name] = [(n, im) for n, im in ims if im is not None]
    return out


# ---------------------------------------------------------------------------------------------- methods


def orb_method(n: int) -> Method:
    orb = cv2.ORB_create(nfeatures=n)

    def run(gray):
        kps, desc = orb.detectAndCompute(gray, None)
        if desc is None:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        return np.array([k.pt for k in kps], np.float64).reshape(-1, 2), desc

    return run


def sift_method(n: int) -> Method:
    sift = cv2.SIFT_create(nfeatures=n)

    def run(gray):
        kps, desc = sift.detectAndCompute(gray, None)
        if desc is None:
            return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
        xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        return xy[:n], desc[:n]

    return run


def convpoint_method(model, n: int, device=None) -> Method:
    from vslam.features.convpoint import DetectSettings, detect_batch

    s = DetectSettings(max_keypoints=n)

    def run(gray):
        xy, _, desc = detect_batch(model, [gray], s, device)[0]
        return xy, desc

    return run


# ---------------------------------------------------------------------------------------------- metrics


def pair_metrics(xa, da, xb, db, H: np.ndarray, shape_a, shape_b, eps: float = 3.0) -> dict[str, float]:
    """The homography-benchmark numbers of one image pair (x_b ~ H x_a)."""
    from vslam.eval.homography import inside, warp_points

    ha, wa = shape_a
    hb, wb = shape_b
    Hinv = np.linalg.inv(H)
    va = inside(warp_points(H, xa), hb, wb) if len(xa) else np.zeros(0, bool)  # a's keypoints seen by b
    vb = inside(warp_points(Hinv, xb), ha, wa) if len(xb) else np.zeros(0, bool)
    out = {"n_a": float(len(xa)), "n_b": float(len(xb))}
    xa_in_b = warp_points(H, xa[va])
    if va.sum() and vb.sum():
        dist = np.linalg.norm(xa_in_b[:, None] - xb[vb][None], axis=2)
        rep_a, rep_b = dist.min(axis=1) <= eps, dist.min(axis=0) <= eps
        out["repeatability"] = float((rep_a.sum() + rep_b.sum()) / (va.sum() + vb.sum()))
        close = np.concatenate([dist.min(axis=1)[rep_a], dist.min(axis=0)[rep_b]])
        out["loc_error"] = float(close.mean()) if len(close) else float("nan")
    else:
        out["repeatability"], out["loc_error"] = 0.0, float("nan")
    m = match_mutual(da, db, ratio=None)
    err = np.linalg.norm(warp_points(H, xa[m[:, 0]]) - xb[m[:, 1]], axis=1) if len(m) else np.zeros(0)
    shared = 0.5 * (va.sum() + vb.sum())
    out["matching_score"] = float((err <= eps).sum() / shared) if shared else 0.0
    for t in (1, 3, 5):
        out[f"mma@{t}"] = float((err <= t).mean()) if len(err) else 0.0
    corner_err = np.inf
    if len(m) >= 4:
        Hest, _ = cv2.findHomography(xa[m[:, 0]], xb[m[:, 1]], cv2.RANSAC, 3.0, maxIters=2000, confidence=0.999)
        if Hest is not None:
            c = np.array([[0, 0], [wa - 1, 0], [wa - 1, ha - 1], [0, ha - 1]], np.float64)
            corner_err = float(np.linalg.norm(warp_points(Hest, c) - warp_points(H, c), axis=1).mean())
    for t in (1, 3, 5):
        out[f"h_acc@{t}"] = float(corner_err <= t)
    out["matches"] = float(len(m))
    return out


def _mean(rows: list[dict[str, float]]) -> dict[str, float]:
    keys = rows[0].keys() if rows else []
    return {k: float(np.nanmean([r[k] for r in rows])) for k in keys}


def homography_benchmark(methods: dict[str, Method], images: dict[str, list[tuple[str, np.ndarray]]],
                         cfg: FeatureBenchConfig = FeatureBenchConfig(), progress: Progress | None = None) -> dict:
    """-> {condition: {method: mean metrics}} over every pair, plus ms per image per method. ``progress(methods
    done, methods)``."""
    from vslam.eval.homography import HomographySpec, illumination_change, random_homography, warp

    rng = np.random.default_rng(cfg.seed)
    pairs = []  # the same pairs for every method
    for src, ims in images.items():
        for name, im in ims:
            h, w = im.shape
            for _ in range(cfg.pairs_per_image):
                H = random_homography(rng, h, w, HomographySpec(scale=(0.8, 1.2), rotation_deg=20, perspective=0.1,
                                                                shift=0.05))
                b = warp(im, H)
                pairs.append((src, im, H, {"viewpoint": b, "illumination": illumination_change(b, rng)}))
    res: dict = {"viewpoint": {}, "illumination": {}, "ms_per_image": {}, "pairs": len(pairs)}
    for mname, fn in methods.items():
        rows = {"viewpoint": [], "illumination": []}
        t, n_calls = 0.0, 0
        for src, a, H, bs in pairs:
            t0 = time.perf_counter()
            xa, da = fn(a)
            t += time.perf_counter() - t0
            n_calls += 1
            for cond, b in bs.items():
                t0 = time.perf_counter()
                xb, db = fn(b)
                t += time.perf_counter() - t0
                n_calls += 1
                rows[cond].append(pair_metrics(xa, da, xb, db, H, a.shape, b.shape, cfg.eps_px))
        for cond in rows:
            res[cond][mname] = _mean(rows[cond])
        res["ms_per_image"][mname] = 1000 * t / max(n_calls, 1)
        if progress is not None:
            progress(len(res["ms_per_image"]), len(methods))
    return res


def epipolar_sequences(root: Path) -> dict[str, tuple[str, int]]:
    """The held-out sequences of the epipolar check that ``root`` holds: {name: (folder, first held-out frame)}."""
    from vslam.train.keypoint_data import KeypointSplits

    tc = KeypointSplits()
    seqs = {"tum": (tc.tum, tc.tum_split), "kitti": (tc.kitti, tc.kitti_split)}
    return {name: (rel, split) for name, (rel, split) in seqs.items() if (root / rel).exists()}


def epipolar_benchmark(methods: dict[str, Method], root: Path, cfg: FeatureBenchConfig = FeatureBenchConfig(),
                       progress: Progress | None = None) -> dict:
    """-> {sequence: {method: {inlier_ratio, matches, pairs}}} on held-out consecutive frames with true poses.
    ``progress(done, sequences x methods)`` after each method on each sequence."""
    from vslam.data.registry import open_sequence

    gaps = cfg.gap or {"tum": 5, "kitti": 2}
    seqs = epipolar_sequences(root)
    out = {}
    for name, (rel, split) in seqs.items():
        seq = open_sequence(root / rel)
        cam = seq.calibration.cam0
        frames = [f for f in seq if f.index >= split and f.T_world_cam is not None]
        pick = frames[:: max(1, gaps[name] * 2)]
        by_index = {f.index: f for f in frames}
        pairs = [(f, by_index[f.index + gaps[name]]) for f in pick if f.index + gaps[name] in by_index][: cfg.max_images_per_source]
        out[name] = {}
        for mname, fn in methods.items():
            ratios, counts = [], []
            for f1, f2 in pairs:
                g1, g2 = (cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) if f.image.ndim == 3 else f.image for f in (f1, f2))
                x1, d1 = fn(g1)
                x2, d2 = fn(g2)
                m = match_mutual(d1, d2, ratio=0.9)
                if len(m) == 0:
                    ratios.append(0.0)
                    counts.append(0)
                    continue
                u1, u2 = cam.undistort_points(x1[m[:, 0]]), cam.undistort_points(x2[m[:, 1]])
                ratios.append(float((symmetric_epipolar(u1, u2, f1.T_world_cam, f2.T_world_cam, cam.K) < 1.0).mean()))
                counts.append(len(m))
            out[name][mname] = {"inlier_ratio": float(np.mean(ratios)) if ratios else 0.0,
                                "matches": float(np.mean(counts)) if counts else 0.0, "pairs": len(pairs)}
            if progress is not None:
                progress(sum(map(len, out.values())), len(seqs) * len(methods))
    return out


def symmetric_epipolar(u1: np.ndarray, u2: np.ndarray, T_w1: np.ndarray, T_w2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N,) pixel distance of each match to the other's epipolar line (max over both images)."""
    F = fundamental(T_w1, T_w2, K)  # x2^T F x1 = 0
    h1, h2 = np.c_[u1, np.ones(len(u1))], np.c_[u2, np.ones(len(u2))]
    l2, l1 = h1 @ F.T, h2 @ F
    e = np.abs((h2 * l2).sum(axis=1))
    return np.maximum(e / np.maximum(np.linalg.norm(l2[:, :2], axis=1), 1e-12),
                      e / np.maximum(np.linalg.norm(l1[:, :2], axis=1), 1e-12))


def time_methods(methods: dict[str, Method], image: np.ndarray, repeat: int = 10) -> dict[str, float]:
    """Median ms per call of each method on one image (after a warm-up call): the 640x480 inference row."""
    out = {}
    for name, fn in methods.items():
        fn(image)
        ts = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn(image)
            ts.append(time.perf_counter() - t0)
        out[name] = 1000 * float(np.median(ts))
    return out


def run_feature_bench(weights: str | Path, root: Path, cfg: FeatureBenchConfig = FeatureBenchConfig(),
                      methods: tuple[str, ...] = ("orb", "sift", "convpoint", "convpoint-int8"),
                      progress: Progress | None = None) -> dict:
    """The full evaluation of ``weights`` against ORB and SIFT, one run, one set of pairs. "convpoint-int8": the
    same network quantised for the CPU (``FeatureConfig.int8``; its ranges must be beside the weights).
    ``progress(done, total)`` after each method's pass of each benchmark (the homography one, then per sequence)."""
    import torch

    from vslam.features.convpoint import load_convpoint

    make = {"orb": lambda: orb_method(cfg.n_keypoints), "sift": lambda: sift_method(cfg.n_keypoints),
            "convpoint": lambda: convpoint_method(load_convpoint(weights), cfg.n_keypoints),
            "convpoint-int8": lambda: convpoint_method(load_convpoint(weights, int8=True), cfg.n_keypoints, torch.device("cpu"))}
    unknown = [m for m in methods if m not in make]
    if unknown:
        from vslam.errors import ConfigError

        raise ConfigError(f"unknown feature method(s) {', '.join(unknown)} (known: {', '.join(make)})")
    fns = {m: make[m]() for m in methods}
    images = held_out_images(root, cfg.max_images_per_source)
    if not any(images.values()):
        from vslam.errors import DatasetError

        raise DatasetError(root, "no held-out images found (COCO128 / TUM / KITTI / EuRoC subsets; set VSLAM_DATA)")
    n_hom, n_all = len(fns), len(fns) * (1 + len(epipolar_sequences(root)))

    def after(skip: int) -> Progress | None:  # one count over both benchmarks
        return None if progress is None else lambda done, total: progress(skip + done, n_all)

    res = {"homography": homography_benchmark(fns, images, cfg, after(0)), "epipolar": epipolar_benchmark(fns, root, cfg, after(n_hom)),
           "images": {k: len(v) for k, v in images.items()}, "n_keypoints": cfg.n_keypoints}
    vga = next((im for _, ims in images.items() for _, im in ims if im.shape == (480, 640)), None)
    if vga is not None:
        res["ms_640x480"] = time_methods(fns, vga)
        res["threads"] = torch.get_num_threads()
    return res


def evaluate_convpoint_model(model, root: Path) -> dict:
    """The trainer's final check: the homography benchmark of ConvPoint alone (ORB/SIFT via eval-features)."""
    images = held_out_images(root, 6)
    if not any(images.values()):
        return {}
    return homography_benchmark({"convpoint": convpoint_method(model, 1000)}, images, FeatureBenchConfig(pairs_per_image=1))


def format_table(res: dict) -> list[str]:
    """Markdown tables of ``run_feature_bench``'s result."""
    hom = res["homography"]
    lines = [f"{hom['pairs']} pairs from held-out images {res['images']}, {res['n_keypoints']} keypoints per image, "
             "mutual nearest neighbours.", "",
             "| condition | method | repeatability | loc. error px | matching score | MMA@1 | MMA@3 | MMA@5 | H acc@1 | H acc@3 | H acc@5 | ms / image |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for cond in ("viewpoint", "illumination"):
        for m, r in hom[cond].items():
            lines.append(f"| {cond} | {m} | {r['repeatability']:.3f} | {r['loc_error']:.2f} | {r['matching_score']:.3f} | "
                         f"{r['mma@1']:.3f} | {r['mma@3']:.3f} | {r['mma@5']:.3f} | {r['h_acc@1']:.3f} | {r['h_acc@3']:.3f} | "
                         f"{r['h_acc@5']:.3f} | {hom['ms_per_image'][m]:.1f} |")
    if res.get("ms_640x480"):
        lines += ["", f"Inference on one 640x480 frame, median of 10, {res.get('threads', '?')} CPU threads (ConvPoint: network + "
                  "NMS + descriptors; ORB / SIFT: OpenCV detect + compute): " +
                  ", ".join(f"{m} {ms:.1f} ms" for m, ms in res["ms_640x480"].items()) + "."]
    if res.get("epipolar"):
        lines += ["", "| sequence (held-out frames) | method | pairs | matches | epipolar inlier ratio (< 1 px) |", "|---|---|---|---|---|"]
        for seq, ms in res["epipolar"].items():
            for m, r in ms.items():
                lines.append(f"| {seq} | {m} | {r['pairs']} | {r['matches']:.0f} | {r['inlier_ratio']:.3f} |")
    return lines
