"""Box utilities and non-maximum suppression in plain torch (torchvision is not a dependency).

Boxes are (N, 4) x1, y1, x2, y2 pixels.
"""

from __future__ import annotations

import torch


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,4), (M,4) -> (N,M) intersection over union."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter + 1e-9)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS, exact (same result as torchvision.ops.nms): indices of kept boxes, by decreasing score.

    The IoU matrix is computed once; the greedy pass is a loop over boxes still alive, each step one vectorised
    suppression of everything it overlaps, so the cost is O(N^2) memory and O(kept) Python steps.
    """
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = scores.argsort(descending=True)
    iou = box_iou(boxes[order], boxes[order])
    n = len(order)
    alive = torch.ones(n, dtype=torch.bool, device=boxes.device)
    later = torch.triu(torch.ones(n, n, dtype=torch.bool, device=boxes.device), diagonal=1)
    suppress = (iou > iou_threshold) & later
    keep = []
    i = 0
    while i < n:
        keep.append(i)
        alive &= ~suppress[i]
        nxt = torch.nonzero(alive[i + 1:])
        if len(nxt) == 0:
            break
        i = i + 1 + int(nxt[0])
    return order[torch.tensor(keep, dtype=torch.long, device=boxes.device)]


def batched_nms(boxes: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Class-aware NMS: boxes of different classes never suppress each other (offset trick)."""
    if boxes.numel() == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    offset = classes.to(boxes.dtype)[:, None] * (boxes.max() + 1.0)
    return nms(boxes + offset, scores, iou_threshold)
