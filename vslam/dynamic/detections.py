"""What every detector gives (``Detections``) and the score threshold + class-aware NMS they share
(``postprocess``); the detectors' modules import this one, never each other."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vslam.nn.ops import batched_nms


@dataclass
class Detections:
    """boxes: (K,4) float x1,y1,x2,y2 pixels of the input image; scores: (K,); class_ids: (K,) int;
    class_names: (K,) str; masks: (K,H,W) bool instance masks in the input image's pixels, or None where the
    network has no mask head (then a box is all there is to mask); mask_px: the image pixels one prototype cell
    spans (the masks' resolution: their outlines are uncertain by about half of it)."""

    boxes: np.ndarray
    scores: np.ndarray
    class_ids: np.ndarray
    class_names: np.ndarray
    masks: np.ndarray | None = None
    mask_px: float = 0.0


@torch.no_grad()
def postprocess(boxes: torch.Tensor, probs: torch.Tensor, conf: float, iou: float, max_det: int = 100,
                max_candidates: int = 3000, extra: torch.Tensor | None = None) -> list[tuple[torch.Tensor, ...]]:
    """Per image: (K,4) boxes, (K,) scores, (K,) classes after score threshold and class-aware NMS; with
    ``extra`` (B, A, E) per-anchor values (mask coefficients) also the kept anchors' (K, E)."""
    out = []
    for i, (b, p) in enumerate(zip(boxes, probs)):
        score, cls = p.max(-1)
        keep = torch.nonzero(score > conf).squeeze(1)
        b, score, cls = b[keep], score[keep], cls[keep]
        if len(score) > max_candidates:
            top = score.topk(max_candidates).indices
            b, score, cls, keep = b[top], score[top], cls[top], keep[top]
        k = batched_nms(b, score, cls, iou)[:max_det]
        out.append((b[k], score[k], cls[k]) if extra is None else (b[k], score[k], cls[k], extra[i, keep[k]]))
    return out
