"""``vslam eval-detector DATA``: a detector on a labelled folder of real photos, in the terms SLAM cares
about. Person and vehicle AP50 / AP50-95 (COCO-style, ``metrics``), recall and precision at the score threshold
SLAM masks with, and where the folder has instance masks (Penn-Fudan) the mask IoU of what SLAM masks.

A detector with a mask head masks its instance masks; a box detector masks its boxes, so its "mask" is the filled
box. ``mask_iou`` is the IoU of a matched detection's mask (box IoU >= 0.5, score >= the threshold) with the
instance's true mask; ``box_mask_iou`` the same for the detection's filled box (the baseline a mask head must beat);
``gt_box_mask_iou`` is the same for the annotated box (the best any box can do); ``image_mask_iou`` compares the
union of what the detections mask with the union of the true masks per image (pixels SLAM drops vs pixels it
should).

Detections are mapped to ``EVAL_CLASSES`` by name (``datasets.class_index``): the shipped detector's ``car`` and
FastestDet's COCO car / bus / truck / motorcycle are all ``vehicle``; other classes are dropped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from vslam.errors import ConfigError
from vslam.eval.detection_metrics import detection_report, match
from vslam.train.photos import EVAL_CLASSES, Record, class_index

log = logging.getLogger(__name__)
MATCH_IOU = 0.5  # box IoU for recall, precision and the mask IoU's match (AP50's)


class BoxDetector(Protocol):
    def detect(self, image: np.ndarray) -> Any: ...  # -> Detections (boxes, scores, class_ids, class_names)


@dataclass(frozen=True)
class Prediction:
    """One image's detections in eval classes: boxes (K,4) x1,y1,x2,y2 pixels, scores (K,), classes (K,) int into
    ``EVAL_CLASSES``, masks (K,H,W) bool or None (no mask head)."""

    boxes: np.ndarray
    scores: np.ndarray
    classes: np.ndarray
    masks: np.ndarray | None = None


def predict(det: BoxDetector, records: list[Record], progress: Any = None) -> list[Prediction]:
    """Run ``det`` on every record's image; keep the detections whose class maps to an eval class."""
    out = []
    for n, rec in enumerate(records):
        d = det.detect(rec.image())
        cls = np.array([class_index(str(name), EVAL_CLASSES) for name in d.class_names], dtype=object)
        keep = np.array([c is not None for c in cls], bool)
        masks = getattr(d, "masks", None)
        out.append(Prediction(np.asarray(d.boxes, np.float64)[keep].reshape(-1, 4), np.asarray(d.scores, np.float64)[keep],
                              cls[keep].astype(np.int64), None if masks is None else masks[keep]))
        if progress is not None:
            progress(n + 1, len(records))
    return out


def box_mask(box: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H,W) bool: the pixels of ``box`` (x1,y1,x2,y2, x2/y2 exclusive), rounded to the pixel grid and clipped."""
    h, w = shape
    x1, y1, x2, y2 = np.round(box).astype(int)
    m = np.zeros((h, w), bool)
    m[max(y1, 0):min(y2, h), max(x1, 0):min(x2, w)] = True
    return m


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def evaluate(records: list[Record], preds: list[Prediction], threshold: float) -> dict[str, Any]:
    """-> {"images", "threshold", per class "<metric>/<class>": AP50, AP50-95, recall, precision, n_gt; and where
    the records have masks mask_iou, gt_box_mask_iou, image_mask_iou (+ n_masks)} (module docstring)."""
    gts = [(r.boxes, r.labels) for r in records]
    dets = [(p.boxes, p.scores, p.classes) for p in preds]
    ignore = [r.ignore for r in records]
    rep: dict[str, Any] = {"images": len(records), "threshold": threshold}
    ap = detection_report(dets, gts, list(EVAL_CLASSES), ignore)
    for c, name in enumerate(EVAL_CLASSES):
        n_gt = int(sum((r.labels == c).sum() for r in records))
        rep[f"n_gt/{name}"] = n_gt
        if not n_gt:
            continue
        tp = fp = 0
        for rec, p in zip(records, preds):
            sel = (p.classes == c) & (p.scores >= threshold)
            gt, ign = match(p.boxes[sel], p.scores[sel], rec.boxes[rec.labels == c], MATCH_IOU, rec.ignore)
            tp, fp = tp + int((gt >= 0).sum()), fp + int(((gt < 0) & ~ign).sum())
        rep[f"AP50/{name}"], rep[f"AP75/{name}"], rep[f"AP50-95/{name}"] = (ap[f"AP50/{name}"], ap[f"AP75/{name}"],
                                                                            ap[f"AP50-95/{name}"])
        rep[f"recall/{name}"] = tp / n_gt
        rep[f"precision/{name}"] = tp / (tp + fp) if tp + fp else float("nan")
    rep.update(mask_report(records, preds, threshold))
    return rep


def mask_report(records: list[Record], preds: list[Prediction], threshold: float) -> dict[str, Any]:
    """Mask IoUs of the detections with instance masks ({} when none has any), class by class."""
    inst: dict[int, list[float]] = {}
    boxed: dict[int, list[float]] = {}
    oracle: dict[int, list[float]] = {}
    image: dict[int, list[float]] = {}
    for rec, p in zip(records, preds):
        masks = rec.masks()
        if masks is None:
            continue
        has = rec.mask_ids > 0
        for c in np.unique(rec.labels[has]):
            gm, gb = masks[has & (rec.labels == c)], rec.boxes[has & (rec.labels == c)]
            sel = (p.classes == c) & (p.scores >= threshold)
            db = p.boxes[sel]
            dm = [box_mask(b, gm.shape[1:]) for b in db] if p.masks is None else list(p.masks[sel])
            gt, _ = match(db, p.scores[sel], gb, MATCH_IOU)
            for i in np.nonzero(gt >= 0)[0]:
                inst.setdefault(c, []).append(_iou(dm[i], gm[gt[i]]))
                boxed.setdefault(c, []).append(_iou(box_mask(db[i], gm.shape[1:]), gm[gt[i]]))
            oracle.setdefault(c, []).extend(_iou(box_mask(b, gm.shape[1:]), m) for b, m in zip(gb, gm))
            drop = np.zeros(gm.shape[1:], bool)
            for m in dm:
                drop |= m
            image.setdefault(c, []).append(_iou(drop, gm.any(0)))
    out: dict[str, Any] = {}
    for c, name in enumerate(EVAL_CLASSES):
        if c in oracle:
            out[f"mask_iou/{name}"] = float(np.mean(inst[c])) if inst.get(c) else float("nan")
            out[f"box_mask_iou/{name}"] = float(np.mean(boxed[c])) if boxed.get(c) else float("nan")
            out[f"n_masks/{name}"] = len(inst.get(c, []))
            out[f"gt_box_mask_iou/{name}"] = float(np.mean(oracle[c]))
            out[f"image_mask_iou/{name}"] = float(np.mean(image[c]))
    return out


def format_report(rep: dict[str, Any], title: str) -> list[str]:
    """Markdown table, one row per class with ground truth."""
    masks = any(k.startswith("mask_iou/") for k in rep)
    head = f"| {title} | GT | AP50 | AP75 | AP50-95 | recall@{rep['threshold']:g} | precision@{rep['threshold']:g} |"
    head += " mask IoU (matched) | its box as mask | GT box as mask | image mask IoU |" if masks else ""
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    f = lambda k: f"{rep[k]:.3f}" if rep.get(k) is not None and rep[k] == rep[k] else "–"  # noqa: E731 (NaN, None -> –)
    for name in EVAL_CLASSES:
        if not rep.get(f"n_gt/{name}"):
            continue
        row = f"| {name} | {rep[f'n_gt/{name}']} | {f(f'AP50/{name}')} | {f(f'AP75/{name}')} | {f(f'AP50-95/{name}')} | {f(f'recall/{name}')} | " \
              f"{f(f'precision/{name}')} |"
        if masks:
            row += f" {f(f'mask_iou/{name}')} | {f(f'box_mask_iou/{name}')} | {f(f'gt_box_mask_iou/{name}')} | " \
                   f"{f(f'image_mask_iou/{name}')} |"
        lines.append(row)
    return lines


def build_detector(model: str, teacher: bool, threads: int, img_size: int = 0,
                   wide: bool = False) -> tuple[BoxDetector, float, str]:
    """-> (detector emitting every box above 0.001, its SLAM score threshold, a name). Ours: the checkpoint at
    ``model`` (default the shipped one) at ``img_size`` (0: the size it was trained at, as slam.dynamic.img_size),
    threshold ``DynamicConfig``'s; the teacher: FastestDet (``model`` = its ONNX file, default the data folder's;
    its input is fixed) at ``TEACHER_THRESHOLD``."""
    if teacher:
        from vslam.train.teacher import TEACHER_THRESHOLD, FastestDet

        if img_size:
            raise ConfigError("--img-size sets our detector's input; FastestDet's is fixed (352x352)")

        det = FastestDet(model, threads=threads)
        return det, TEACHER_THRESHOLD, "FastestDet"
    import torch

    from vslam.dynamic.config import DynamicConfig
    from vslam.dynamic.detector import default_weights, load_detector

    torch.set_num_threads(threads)
    if img_size < 0 or img_size % 32:
        raise ConfigError(f"--img-size must be 0 or a positive multiple of 32, got {img_size}")
    path = Path(model) if model else default_weights()
    det = load_detector(path, conf=0.001, field="--model")
    det.img_size = img_size or det.img_size
    if wide and not hasattr(det, "wide"):
        raise ConfigError("--wide is for YOLOX-style detectors (the from-scratch detector always keeps the aspect)")
    if wide:
        det.wide = True
    return det, DynamicConfig().score_threshold, f"{path.name}@{det.img_size}{' wide' if wide else ''}"
