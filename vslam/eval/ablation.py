"""The detector ablation (dynamic-object filtering, seed 003's none / SE / CBAM / ESEA): every weights file on the
same held-out sets, AP50 / AP50-95 per class, parameters, and the cost of the mask step on a 640x480 frame.

The held-out sets are rebuilt from the recipe stored in the first checkpoint (``train``): COCO128 val2017, the
dynamic benchmark's composited TUM frames 100-199 (its walkers' COCO images were never trained on), synthetic
rooms of other seeds. Comparing files trained with different recipes is refused: that would not be an ablation.
"""

from __future__ import annotations

import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vslam.errors import ConfigError


def mask_step_ms(det: Any, image: np.ndarray, n_keypoints: int = 1500, repeats: int = 20) -> float:
    """Median ms of what the SLAM loop pays per frame for masking: detect + keypoints-in-boxes."""
    from vslam.dynamic.masking import in_boxes

    uv = np.random.default_rng(0).uniform([0, 0], [image.shape[1], image.shape[0]], (n_keypoints, 2))
    det.detect(image)  # warm-up (allocations, kernel selection)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        d = det.detect(image)
        in_boxes(uv, d.boxes, 4)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def evaluate_detectors(weights: list[str], threads: int = 2, frame: str = "") -> dict[str, Any]:
    """-> {"models": {file: {"attention", "params", "img_size", "ms_640x480", "sets": {set: report}}}, "sets": sizes}."""
    from vslam.dynamic.detector import Detector, load_model
    from vslam.train.detector import TrainConfig, _recipe, evaluate, held_out_sets

    torch.set_num_threads(threads)
    names = {f.name for f in fields(TrainConfig)}
    loaded, recipe = [], None
    for w in weights:
        model, ckpt = load_model(w)
        train = {k: tuple(v) if isinstance(v, list) else v for k, v in ckpt.get("train", {}).items() if k in names}
        rec = {k: v for k, v in _recipe(train).items() if k not in ("attention", "out")}  # what the ablation varies
        if recipe is None:
            recipe = rec
        elif rec != recipe:
            diff = sorted(k for k in set(rec) | set(recipe) if rec.get(k) != recipe.get(k))
            raise ConfigError(f"{w}: trained with another recipe than {weights[0]} ({', '.join(diff)}); not an ablation")
        loaded.append((w, model, ckpt, train))
    cfg = replace(TrainConfig(**loaded[0][3]), toy=False)
    sets = held_out_sets(cfg)
    image = _frame(frame, sets)
    out: dict[str, Any] = {"models": {}, "sets": {k: len(v) for k, v in sets.items()}}
    dev = torch.device("cpu")
    for w, model, ckpt, _ in loaded:
        size = int(ckpt.get("img_size", cfg.img_size))
        rep = {name: evaluate(model, data, replace(cfg, img_size=size), dev) for name, data in sets.items()}
        det = Detector(model, ckpt["names"], img_size=size, conf=0.25)
        out["models"][Path(w).name] = {
            "attention": model.cfg.attention, "params": sum(p.numel() for p in model.parameters()),
            "img_size": det.img_size, "ms_640x480": mask_step_ms(det, image), "sets": rep}
    return out


def _frame(path: str, sets: dict[str, list]) -> np.ndarray:
    """The timing frame: a given image, else the first composited TUM frame, else a 640x480 synthetic one."""
    import cv2

    if path:
        img = cv2.imread(path, cv2.IMREAD_COLOR)
        if img is None:
            raise ConfigError(f"{path}: not a readable image")
        return img
    if sets.get("tum-people"):
        return sets["tum-people"][0].image
    return np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)


def format_table(res: dict[str, Any]) -> list[str]:
    """Markdown: one row per weights file, AP50 / AP50-95 of person (and car) per held-out set."""
    sets = list(res["sets"])
    head = "| weights | attention | params | " + " | ".join(
        f"{s} ({res['sets'][s]}) person AP50 / AP50-95" for s in sets) + " | car AP50 (coco128-val) | mask step ms, 640x480 |"
    lines = [head, "|---|---|---|" + "---|" * len(sets) + "---|---|"]
    for name, m in res["models"].items():
        cells = []
        for s in sets:
            r = m["sets"][s]
            cells.append(f"{r.get('AP50/person', float('nan')):.3f} / {r.get('AP50-95/person', float('nan')):.3f}")
        car = m["sets"].get("coco128-val", {}).get("AP50/car")
        lines.append(f"| {name} | {m['attention']} | {m['params'] / 1e6:.2f} M | " + " | ".join(cells) +
                     f" | {'–' if car is None else f'{car:.3f}'} | {m['ms_640x480']:.1f} |")
    return lines
