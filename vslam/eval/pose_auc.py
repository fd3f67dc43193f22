"""Two-view relative pose accuracy of keypoint methods: the SuperGlue / LightGlue protocol on real frames with
ground-truth poses.

Per pair: up to ``n_keypoints`` keypoints per image, mutual nearest neighbours of the descriptors (Hamming for
binary, L2 for float; no ratio test), the essential matrix by ``cv2.findEssentialMat`` (RANSAC, ``ransac_px``
pixel threshold in normalised coordinates, i.e. divided by the mean focal length, confidence 0.99999) and
``cv2.recoverPose``; the error of a pair is the larger of the rotation angle error and the angle between the
translation directions (sign-free: the scale and sign of a two-view translation are not observed); a failed
estimate counts as an infinite error. AUC of the error's cumulative curve up to 5, 10 and 20 degrees
(SuperGlue's ``pose_auc``).

Pairs (``pose_pairs``): KITTI 07 frames i, i+k for i = 80, 81, ... (k = 1, 3, 5) and TUM fr3/teddy frames i, i+k
for i = 100, 101, ... (k = 5, 15), ``pairs`` each -- the frames the keypoint networks trained here hold out
(``KeypointTrainConfig.*_split``); they are the validation pairs of the ALIKE choices (resolution, variant).
Extraction time: median wall ms per image of each method, over the images of a sequence, on the threads the
caller set.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from vslam.geometry.se3 import so3_angle_deg

Method = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # BGR or grey uint8 image -> (xy (N,2), desc (N,D))
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class PoseBenchConfig:
    n_keypoints: int = 2000
    pairs: int = 50  # per (sequence, gap)
    ransac_px: float = 1.0
    gaps: dict[str, tuple[int, ...]] = field(default_factory=lambda: {"kitti": (1, 3, 5), "tum": (5, 15)})
    thresholds_deg: tuple[float, ...] = (5.0, 10.0, 20.0)


def sequences(root: Path) -> dict[str, tuple[str, int]]:
    """{name: (folder under ``root``, first frame)} of the sequences ``root`` holds."""
    from vslam.train.keypoints import KeypointTrainConfig

    tc = KeypointTrainConfig()
    seqs = {"kitti": (tc.kitti, tc.kitti_split), "tum": (tc.tum, tc.tum_split)}
    return {k: v for k, v in seqs.items() if (root / v[0]).exists()}


def relative_pose(T_w1: np.ndarray, T_w2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of camera 1 in camera 2: x2 = R x1 + t (what ``recoverPose`` returns for points 1 -> 2)."""
    T21 = np.linalg.inv(T_w2) @ T_w1
    return T21[:3, :3], T21[:3, 3]


def pose_error(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray) -> tuple[float, float]:
    """(rotation error, translation direction error) in degrees; the direction error ignores the sign."""
    err_r = so3_angle_deg(R_est.T @ R_gt)
    n = np.linalg.norm(t_est) * np.linalg.norm(t_gt)
    cos = float(np.dot(t_est.ravel(), t_gt.ravel()) / max(n, 1e-12))
    err_t = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return err_r, min(err_t, 180.0 - err_t)


def estimate_pose(x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray, ransac_px: float
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) from matched pixels (M,2) of two images, or None (fewer than 5 matches, no essential matrix).
    Of several essential matrices OpenCV returns, the one with the most points in front of both cameras."""
    if len(x1) < 5:
        return None
    n1 = (x1 - K1[[0, 1], [2, 2]]) / K1[[0, 1], [0, 1]]
    n2 = (x2 - K2[[0, 1], [2, 2]]) / K2[[0, 1], [0, 1]]
    thresh = ransac_px / np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]])
    E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), threshold=thresh, prob=0.99999, method=cv2.RANSAC)
    if E is None:
        return None
    best, best_n = None, 0
    for Ei in np.split(E, len(E) // 3):
        n, R, t, _ = cv2.recoverPose(Ei, n1, n2, np.eye(3), 1e9, mask=mask.copy())
        if n > best_n:
            best, best_n = (R, t[:, 0]), n
    return best


def pose_auc(errors: list[float] | np.ndarray, thresholds: tuple[float, ...]) -> list[float]:
    """Area under the cumulative error curve up to each threshold, normalised to [0, 1] (SuperGlue's)."""
    e = np.sort(np.asarray(errors, np.float64))
    recall = (np.arange(len(e)) + 1) / len(e)
    e, recall = np.r_[0.0, e], np.r_[0.0, recall]
    out = []
    for t in thresholds:
        last = int(np.searchsorted(e, t))
        r = np.r_[recall[:last], recall[last - 1]]
        x = np.r_[e[:last], t]
        out.append(float(np.trapezoid(r, x) / t))
    return out


def mutual_nn(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    from vslam.features.matching import match_mutual

    return match_mutual(d1, d2, ratio=None)


def pose_benchmark(methods: dict[str, Method], root: Path, cfg: PoseBenchConfig = PoseBenchConfig(),
                   progress: Progress | None = None) -> dict:
    """-> {"<seq>_k<gap>": {method: {auc@5, auc@10, auc@20, matches, failed, pairs}}, "ms": {seq: {method: ms}},
    "pairs": ...}. ``progress(done, total)`` after each method on each sequence."""
    from vslam.data.registry import open_sequence
    from vslam.errors import DatasetError

    seqs = sequences(root)
    if not seqs:
        raise DatasetError(root, "neither KITTI 07 nor TUM fr3/teddy found (set VSLAM_DATA)")
    out: dict = {"ms": {}}
    total, done = len(seqs) * len(methods), 0
    for name, (rel, first) in seqs.items():
        seq = open_sequence(root / rel)
        K = seq.calibration.cam0.K
        frames = {f.index: f for f in seq if f.index >= first and f.T_world_cam is not None}
        pairs = {k: [(i, i + k) for i in range(first, first + cfg.pairs) if i in frames and i + k in frames]
                 for k in cfg.gaps[name]}
        needed = sorted({i for ps in pairs.values() for p in ps for i in p})
        images = {i: frames[i].image for i in needed}
        out["ms"][name] = {}
        for mname, fn in methods.items():
            fn(images[needed[0]])  # warm-up (first-call allocations, lazy initialisation)
            feats, ts = {}, []
            for i in needed:
                t0 = time.perf_counter()
                feats[i] = fn(images[i])
                ts.append(time.perf_counter() - t0)
            out["ms"][name][mname] = 1000.0 * float(np.median(ts))
            for k, ps in pairs.items():
                errs, counts = [], []
                for i, j in ps:
                    (x1, d1), (x2, d2) = feats[i], feats[j]
                    m = mutual_nn(d1, d2) if len(d1) and len(d2) else np.zeros((0, 2), np.int64)
                    counts.append(len(m))
                    est = estimate_pose(x1[m[:, 0]], x2[m[:, 1]], K, K, cfg.ransac_px)
                    if est is None:
                        errs.append(np.inf)
                        continue
                    R_gt, t_gt = relative_pose(frames[i].T_world_cam, frames[j].T_world_cam)
                    errs.append(max(pose_error(est[0], est[1], R_gt, t_gt)))
                auc = pose_auc(errs, cfg.thresholds_deg)
                res = {f"auc@{t:g}": 100.0 * a for t, a in zip(cfg.thresholds_deg, auc)}
                res.update(matches=float(np.mean(counts)), failed=int(np.sum(~np.isfinite(errs))), pairs=len(ps))
                out.setdefault(f"{name}_k{k}", {})[mname] = res
            done += 1
            if progress is not None:
                progress(done, total)
    out["n_keypoints"], out["ransac_px"] = cfg.n_keypoints, cfg.ransac_px
    return out


def standard_methods(n: int, names: tuple[str, ...]) -> dict[str, Method]:
    """Methods by name: "orb", "sift" (OpenCV, grey), "convpoint" (int8), "alike-t" / "alike-s" / "alike-n" at full resolution,
    "<alike>@0.5" at half (the shipped weights, descriptors at the keypoints only), "<alike>[@s]+onnxruntime" with the
    network's dense part in onnxruntime (``features.runtime``)."""
    from vslam.errors import ConfigError
    from vslam.eval.keypoints import orb_method, sift_method

    def grey(fn: Method) -> Method:
        return lambda im: fn(im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))

    out: dict[str, Method] = {}
    for name in names:
        head, _, runtime = name.partition("+")
        base, _, scale = head.partition("@")
        if base == "orb":
            out[name] = grey(orb_method(n))
        elif base == "sift":
            out[name] = grey(sift_method(n))
        elif base == "convpoint":  # the shipped network trained here, int8 on the CPU as SLAM runs it
            import torch

            from vslam.eval.keypoints import convpoint_method
            from vslam.features.convpoint import default_weights, load_convpoint

            out[name] = grey(convpoint_method(load_convpoint(default_weights(), int8=True), n, torch.device("cpu")))
        elif base in ("alike-t", "alike-s", "alike-n"):
            from vslam.features.alike import extract, load_alike, make_maps

            model, s = load_alike(base), float(scale or 1.0)
            maps = make_maps(model, runtime or "torch")
            out[name] = (lambda model, s, maps: lambda im: extract(model, im, n, s, maps=maps)[::2])(model, s, maps)
        else:
            raise ConfigError(f"pose bench: unknown method {name!r} (known: orb, sift, convpoint, alike-t, alike-s, alike-n, "
                              f"with @<scale> and +onnxruntime for the ALIKE ones)")
    return out


def format_table(res: dict) -> list[str]:
    """Markdown rows: method | AUC@5/10/20 per pair set | ms per sequence."""
    sets = [k for k, v in res.items() if k != "ms" and isinstance(v, dict)]  # "<seq>_k<gap>"
    methods = list(res[sets[0]]) if sets else []
    head = "| method | " + " | ".join(s.replace("_k", " k=") for s in sets) + " | " + \
        " | ".join(f"ms {s}" for s in res["ms"]) + " |"
    lines = [head, "|" + "---|" * (1 + len(sets) + len(res["ms"]))]
    for m in methods:
        cells = ["/".join(f"{res[s][m][f'auc@{t}']:.0f}" for t in (5, 10, 20)) for s in sets]
        ms = [f"{res['ms'][s][m]:.0f}" for s in res["ms"]]
        lines.append(f"| {m} | " + " | ".join(cells) + " | " + " | ".join(ms) + " |")
    return lines
