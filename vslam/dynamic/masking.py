"""Mask application: which keypoints fall on dynamic objects (pixel masks or boxes)."""

from __future__ import annotations

import cv2
import numpy as np


def dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """(H,W) bool mask grown by ``px`` pixels (square structuring element)."""
    if px <= 0:
        return mask.astype(bool)
    kernel = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def in_mask(raw_uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N,2) raw pixel coordinates (x, y) -> (N,) bool, True where the rounded pixel is set in ``mask``.
    Keypoints outside the image count as not masked."""
    uv = np.rint(np.asarray(raw_uv, dtype=np.float64)).astype(np.int64).reshape(-1, 2)
    h, w = mask.shape[:2]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    out = np.zeros(len(uv), bool)
    out[inside] = mask[uv[inside, 1], uv[inside, 0]]
    return out


def in_boxes(raw_uv: np.ndarray, boxes: np.ndarray, pad: float = 0.0, grow: float = 0.0) -> np.ndarray:
    """(N,2) pixels, (K,4) boxes x1,y1,x2,y2 -> (N,) bool, True inside any box grown on each side by ``pad``
    pixels plus ``grow`` times its width (left/right) or height (top/bottom)."""
    uv = np.asarray(raw_uv, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(b) == 0 or len(uv) == 0:
        return np.zeros(len(uv), bool)
    x, y = uv[:, 0:1], uv[:, 1:2]
    px = pad + grow * (b[:, 2] - b[:, 0])
    py = pad + grow * (b[:, 3] - b[:, 1])
    hit = (x >= b[:, 0] - px) & (x <= b[:, 2] + px) & (y >= b[:, 1] - py) & (y <= b[:, 3] + py)
    return hit.any(axis=1)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,4), (M,4) boxes x1,y1,x2,y2 -> (K,M) intersection over union."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = w * h
    area = lambda x: (x[:, 2] - x[:, 0]) * (x[:, 3] - x[:, 1])  # noqa: E731
    union = area(a)[:, None] + area(b)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
