"""Box overlap and non-maximum suppression: the one copy the detectors, their training and evaluation and the
dynamic filter share. Plain torch / numpy; importing this module does not import torch (torchvision is a test-time dependency only: tests/nn/test_ops.py checks
these against ``torchvision.ops`` on random and tied boxes).

Boxes are (N, 4) x1, y1, x2, y2 pixels.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # tensor methods only below: the numpy half serves the SLAM filter without importing torch
    import torch


def box_intersection_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,4), (M,4) boxes -> (K,M) areas of their intersections (float64)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    return w * h


def box_iou_np(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,4), (M,4) boxes -> (K,M) intersection over union in float64; 0 where both boxes are empty."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    inter = box_intersection_np(a, b)
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    union = area(a)[:, None] + area(b)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,4), (M,4) -> (N,M) intersection over union (torch, on the boxes' device)."""
    lt = a[:, None, :2].maximum(b[None, :, :2])
    rb = a[:, None, 2:].minimum(b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter + 1e-9)


def box_iou_paired(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(N,4), (N,4) -> (N,) IoU of a[i] with b[i]: ``box_iou``'s diagonal without its (N,N) matrix."""
    lt = a[:, :2].maximum(b[:, :2])
    rb = a[:, 2:].minimum(b[:, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a + area_b - inter + 1e-9)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS, exact (same result as torchvision.ops.nms): indices of kept boxes, by decreasing score.

    The IoU matrix is computed once; the greedy pass is a loop over boxes still alive, each step one vectorised
    suppression of everything it overlaps, so the cost is O(N^2) memory and O(kept) Python steps.
    """
    if boxes.numel() == 0:
        return scores.argsort()  # empty, of the index dtype
    order = scores.argsort(descending=True)
    iou = box_iou(boxes[order], boxes[order])
    n = len(order)
    alive = iou.new_ones(n) > 0
    later = iou.new_ones((n, n)).triu(diagonal=1) > 0
    suppress = (iou > iou_threshold) & later
    keep = []
    i = 0
    while i < n:
        keep.append(i)
        alive &= ~suppress[i]
        nxt = alive[i + 1:].nonzero()
        if len(nxt) == 0:
            break
        i = i + 1 + int(nxt[0])
    return order[order.new_tensor(keep)]


def batched_nms(boxes: torch.Tensor, scores: torch.Tensor, classes: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Class-aware NMS: boxes of different classes never suppress each other (offset trick)."""
    if boxes.numel() == 0:
        return scores.argsort()
    offset = classes.to(boxes.dtype)[:, None] * (boxes.max() + 1.0)
    return nms(boxes + offset, scores, iou_threshold)
