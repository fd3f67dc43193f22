"""Detection metrics: per-class average precision at IoU thresholds (COCO-style 101-point interpolation)."""

from __future__ import annotations

import numpy as np

from vslam.nn.ops import box_iou_np

IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)  # COCO's AP50-95 thresholds (pycocotools: the same linspace)


def match(db: np.ndarray, ds: np.ndarray, gb: np.ndarray, iou_thr: float,
          ignore: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching of one image's detections of one class, best score first, each to the unmatched ground
    truth box of highest IoU (>= ``iou_thr``), as pycocotools' COCOeval. ``ignore`` (M,4): regions (KITTI
    DontCare) treated as COCO crowd boxes: a detection left unmatched whose intersection covers ``iou_thr`` of
    its own area is ignored. -> gt (K,) int, the ground truth box each detection matched or -1, and ignored (K,)
    bool, both in the order of ``db``."""
    k = len(db)
    gt, ign = np.full(k, -1, np.int64), np.zeros(k, bool)
    order = np.argsort(-ds, kind="stable")
    used = np.zeros(len(gb), bool)
    iou = box_iou_np(db[order], gb) if len(gb) and k else np.zeros((k, 0))
    for r, i in enumerate(order):
        j = int(np.argmax(np.where(used, -1, iou[r]))) if len(gb) else -1
        if j >= 0 and not used[j] and iou[r, j] >= iou_thr:
            used[j], gt[i] = True, j
    if ignore is not None and len(ignore) and k:
        lt = np.maximum(db[:, None, :2], ignore[None, :, :2])
        rb = np.minimum(db[:, None, 2:], ignore[None, :, 2:])
        inter = np.clip(rb - lt, 0, None).prod(-1)
        area = np.clip(db[:, 2:] - db[:, :2], 0, None).prod(-1)
        ign = (gt < 0) & ((inter / np.maximum(area, 1e-9)[:, None]) >= iou_thr).any(1)
    return gt, ign


def average_precision(dets: list[tuple[np.ndarray, np.ndarray, np.ndarray]], gts: list[tuple[np.ndarray, np.ndarray]],
                      cls: int, iou_thr: float, ignore: list[np.ndarray] | None = None) -> float:
    """dets per image: (boxes (K,4), scores (K,), classes (K,)); gts per image: (boxes (G,4), classes (G,));
    ``ignore`` per image: (M,4) regions of any class (``match``). -> AP of class ``cls`` (NaN when the class has no
    ground truth). Same numbers as pycocotools' AP for one category, area "all", at most 100 detections per image
    (tests/eval/test_detector.py)."""
    n_gt = sum(int((g[1] == cls).sum()) for g in gts)
    if n_gt == 0:
        return float("nan")
    scores, tps = [], []
    for n, ((db, ds, dc), (gb, gc)) in enumerate(zip(dets, gts)):
        db, ds = db[dc == cls], ds[dc == cls]
        gt, ign = match(db, ds, gb[gc == cls], iou_thr, None if ignore is None else ignore[n])
        scores += list(ds[~ign])
        tps += list(gt[~ign] >= 0)
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


def detection_report(dets: list, gts: list, names: list[str], ignore: list[np.ndarray] | None = None) -> dict[str, float]:
    """{AP50/<name>, AP75/<name>, AP50-95/<name>} per class with ground truth, plus mAP50 and mAP50-95 over those
    classes."""
    out: dict[str, float] = {}
    ap50s, ap5095s = [], []
    for c, name in enumerate(names):
        ap50 = average_precision(dets, gts, c, 0.5, ignore)
        if np.isnan(ap50):
            continue
        aps = [average_precision(dets, gts, c, t, ignore) for t in IOU_THRESHOLDS]
        ap = float(np.mean(aps))
        out[f"AP50/{name}"], out[f"AP75/{name}"], out[f"AP50-95/{name}"] = ap50, aps[5], ap  # thresholds[5] = 0.75
        ap50s.append(ap50)
        ap5095s.append(ap)
    out["mAP50"] = float(np.mean(ap50s)) if ap50s else float("nan")
    out["mAP50-95"] = float(np.mean(ap5095s)) if ap5095s else float("nan")
    return out
