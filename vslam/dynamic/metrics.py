"""Detection metrics: per-class average precision at IoU thresholds (COCO-style 101-point interpolation)."""

from __future__ import annotations

import numpy as np


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(-1)
    area = lambda x: np.clip(x[:, 2:] - x[:, :2], 0, None).prod(-1)  # noqa: E731
    return inter / (area(a)[:, None] + area(b)[None, :] - inter + 1e-9)


def average_precision(dets: list[tuple[np.ndarray, np.ndarray, np.ndarray]], gts: list[tuple[np.ndarray, np.ndarray]],
                      cls: int, iou_thr: float) -> float:
    """dets per image: (boxes (K,4), scores (K,), classes (K,)); gts per image: (boxes (G,4), classes (G,)).
    -> AP of class ``cls`` (NaN when the class has no ground truth)."""
    n_gt = sum(int((g[1] == cls).sum()) for g in gts)
    if n_gt == 0:
        return float("nan")
    scores, tps = [], []
    for (db, ds, dc), (gb, gc) in zip(dets, gts):
        db, ds = db[dc == cls], ds[dc == cls]
        gb = gb[gc == cls]
        order = np.argsort(-ds, kind="stable")
        used = np.zeros(len(gb), bool)
        iou = _iou(db[order], gb) if len(gb) and len(db) else np.zeros((len(db), 0))
        for r, i in enumerate(order):
            j = int(np.argmax(np.where(used, -1, iou[r]))) if len(gb) else -1
            tp = j >= 0 and not used[j] and iou[r, j] >= iou_thr
            if tp:
                used[j] = True
            scores.append(ds[i])
            tps.append(tp)
    if not scores:
        return 0.0
    o = np.argsort(-np.array(scores), kind="stable")
    tp = np.array(tps, float)[o]
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    recall, precision = ctp / n_gt, ctp / np.maximum(ctp + cfp, 1e-9)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # monotone envelope
    rs = np.linspace(0, 1, 101)
    idx = np.searchsorted(recall, rs, side="left")
    return float(np.mean([precision[i] if i < len(precision) else 0.0 for i in idx]))


def detection_report(dets: list, gts: list, names: list[str]) -> dict[str, float]:
    """{AP50/<name>, AP50-95/<name>} per class with ground truth, plus mAP50 and mAP50-95 over those classes."""
    out: dict[str, float] = {}
    ap50s, ap5095s = [], []
    for c, name in enumerate(names):
        ap50 = average_precision(dets, gts, c, 0.5)
        if np.isnan(ap50):
            continue
        ap = float(np.mean([average_precision(dets, gts, c, t) for t in np.arange(0.5, 0.96, 0.05)]))
        out[f"AP50/{name}"], out[f"AP50-95/{name}"] = ap50, ap
        ap50s.append(ap50)
        ap5095s.append(ap)
    out["mAP50"] = float(np.mean(ap50s)) if ap50s else float("nan")
    out["mAP50-95"] = float(np.mean(ap5095s)) if ap5095s else float("nan")
    return out
