"""Mask application: which keypoints fall on dynamic objects (pixel masks or boxes)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vslam.nn.ops import box_intersection_np as box_intersection, box_iou_np as box_iou  # noqa: F401 (re-exported)


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


@dataclass(frozen=True)
class InstanceMask:
    """One detection's pixels within its box: ``pixels`` (h,w) bool covers image rows y0..y0+h-1 and columns
    x0..x0+w-1 (a crop, so a frame's instances and the box memory stay small and cheap to union)."""

    x0: int
    y0: int
    pixels: np.ndarray


@dataclass(frozen=True)
class Instances:
    """One frame's dynamic objects from the detector(s): ``boxes`` (K,4) float64 x1,y1,x2,y2 pixels; ``masks``
    (K,) the box's ``InstanceMask``, or None where the whole box is masked (no mask head, a mask too small to
    trust, ``slam.dynamic.mask=box``, a box followed by ``box_track_s``)."""

    boxes: np.ndarray
    masks: tuple[InstanceMask | None, ...]

    def __len__(self) -> int:
        return len(self.boxes)

    @staticmethod
    def from_boxes(boxes: np.ndarray) -> Instances:
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        return Instances(b, (None,) * len(b))

    @staticmethod
    def concat(parts: list[Instances]) -> Instances:
        return Instances(np.concatenate([p.boxes for p in parts]).reshape(-1, 4) if parts else np.zeros((0, 4)),
                         tuple(m for p in parts for m in p.masks))

    def subset(self, keep: np.ndarray) -> Instances:
        """``keep``: (K,) bool."""
        return Instances(self.boxes[keep], tuple(m for m, k in zip(self.masks, keep) if k))


def crop_mask(mask: np.ndarray, box: np.ndarray, min_fill: float) -> InstanceMask | None:
    """(H,W) bool instance mask and its (4,) box -> the mask's pixels within the box (pixel centres x1 <= x <= x2,
    y1 <= y <= y2: it never masks more than its box), or None when they cover less than ``min_fill`` of the box's
    pixels in the image (an empty or broken mask: the box is safer)."""
    h, w = mask.shape[:2]
    x0, y0 = max(int(np.ceil(box[0])), 0), max(int(np.ceil(box[1])), 0)
    x1, y1 = min(int(np.floor(box[2])), w - 1), min(int(np.floor(box[3])), h - 1)
    if x1 < x0 or y1 < y0:
        return None
    pixels = np.array(mask[y0:y1 + 1, x0:x1 + 1], dtype=bool)  # a copy: the full (K,H,W) masks are not kept
    n = int(np.count_nonzero(pixels))
    if n == 0 or n < min_fill * pixels.size:
        return None
    return InstanceMask(x0, y0, pixels)


def grow_in_box(mask: np.ndarray, box: np.ndarray, px: int) -> np.ndarray:
    """(H,W) bool mask grown by ``px`` pixels, computed only in its box's window (what ``crop_mask`` keeps)."""
    if px <= 0:
        return mask
    h, w = mask.shape[:2]
    x0, y0 = max(int(np.floor(box[0])) - px, 0), max(int(np.floor(box[1])) - px, 0)
    x1, y1 = min(int(np.ceil(box[2])) + px + 1, w), min(int(np.ceil(box[3])) + px + 1, h)
    out = np.zeros((h, w), bool)
    if x1 > x0 and y1 > y0:
        out[y0:y1, x0:x1] = dilate(mask[y0:y1, x0:x1], px)
    return out


def paint(masks: list[InstanceMask], shape: tuple[int, int]) -> np.ndarray:
    """(H,W) bool union of instance masks."""
    out = np.zeros(shape, bool)
    for m in masks:
        h, w = m.pixels.shape
        out[m.y0:m.y0 + h, m.x0:m.x0 + w] |= m.pixels[:max(shape[0] - m.y0, 0), :max(shape[1] - m.x0, 0)]
    return out
