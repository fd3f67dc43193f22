"""Detector training data: YOLO-format folders (COCO128) and synthetic frames with their exact mover boxes.

A sample is (image (H,W,3) uint8 BGR, boxes (K,4) float x1,y1,x2,y2 pixels, labels (K,) int into the training
class list). Augmentation (random scale / placement on a square canvas, horizontal flip, HSV jitter) draws from
the ``np.random.Generator`` it is given, so a run is reproducible and resumable per iteration.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vslam.errors import DatasetError

log = logging.getLogger(__name__)


@dataclass
class Sample:
    image: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray


def _read_names(root: Path) -> list[str]:
    import yaml

    path = root / "names.yaml"
    if not path.is_file():
        raise DatasetError(path, "missing (a YOLO dataset needs names.yaml)")
    names = yaml.safe_load(path.read_text())["names"]
    return [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)


def load_yolo(root: str | Path, split: str, classes: tuple[str, ...], max_side: int = 640,
              skip: frozenset[str] = frozenset()) -> list[Sample]:
    """``root/images/<split>/*.jpg`` with ``root/labels/<split>/*.txt`` (class cx cy w h, normalised).
    Boxes of classes not in ``classes`` are dropped; images are downscaled so the longer side is ``max_side``;
    images whose stem is in ``skip`` are left out."""
    root = Path(root)
    names = _read_names(root)
    to_ours = {i: classes.index(n) for i, n in enumerate(names) if n in classes}
    out = []
    for img_path in sorted((root / "images" / split).glob("*.jpg")):
        if img_path.stem in skip:
            continue
        img = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
        if img is None:
            log.warning("%s: does not decode; skipped", img_path)
            continue
        h, w = img.shape[:2]
        r = min(1.0, max_side / max(h, w))
        if r < 1.0:
            img = cv2.resize(img, (round(w * r), round(h * r)), interpolation=cv2.INTER_AREA)
        lab_path = root / "labels" / split / (img_path.stem + ".txt")
        rows = np.loadtxt(lab_path, ndmin=2) if lab_path.is_file() and lab_path.stat().st_size else np.zeros((0, 5))
        keep = np.array([int(c) in to_ours for c in rows[:, 0]], bool) if len(rows) else np.zeros(0, bool)
        rows = rows[keep]
        cx, cy, bw, bh = rows[:, 1] * w * r, rows[:, 2] * h * r, rows[:, 3] * w * r, rows[:, 4] * h * r
        boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], 1)
        labels = np.array([to_ours[int(c)] for c in rows[:, 0]], np.int64)
        out.append(Sample(img, boxes.reshape(-1, 4), labels))
    if not out:
        raise DatasetError(root / "images" / split, "no images")
    return out


def synthetic_samples(seeds: tuple[int, ...], n_frames: int, stride: int, person: int, n_movers: int = 6,
                      width: int = 640, height: int = 480) -> list[Sample]:
    """Frames of synthetic rooms with ``n_movers`` people-sized movers; their exact boxes labelled ``person``.
    Frames without a visible mover are kept too (negatives), every ``stride``-th frame."""
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

    out = []
    for seed in seeds:
        seq = SyntheticSequence(SyntheticConfig(n_frames=n_frames, seed=seed, n_movers=n_movers, width=width, height=height))
        for i, fr in enumerate(seq):
            if i % stride:
                continue
            boxes = np.zeros((0, 4)) if fr.boxes is None else np.asarray(fr.boxes, np.float64).reshape(-1, 4)
            boxes = boxes[((boxes[:, 2] - boxes[:, 0]) > 4) & ((boxes[:, 3] - boxes[:, 1]) > 4)]
            img = fr.image if fr.image.ndim == 3 else cv2.cvtColor(fr.image, cv2.COLOR_GRAY2BGR)
            out.append(Sample(img, boxes, np.full(len(boxes), person, np.int64)))
    return out


def _hsv_jitter(img: np.ndarray, rng: np.random.Generator, h: float = 0.015, s: float = 0.7, v: float = 0.4) -> np.ndarray:
    """Random gains on hue, saturation and value. Each output byte is a function of its input byte alone, so the
    float arithmetic runs once per possible value (a 256-entry table per channel, ``cv2.LUT``) instead of once
    per pixel: the same bytes as the per-pixel formula (``tests/dynamic/test_train.py``), 7.5x cheaper."""
    gains = rng.uniform(-1, 1, 3) * (h, s, v) + 1
    levels = np.arange(256, dtype=np.float32)
    table = np.empty((256, 3), np.float32)  # float32 like the per-pixel formula's image, then truncated to bytes
    table[:, 0] = (levels * gains[0]) % 180
    table[:, 1:] = np.clip(levels[:, None] * gains[1:], 0, 255)
    hsv = cv2.LUT(cv2.cvtColor(img, cv2.COLOR_BGR2HSV), table.astype(np.uint8).reshape(256, 1, 3))
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)


def place(sample: Sample, size: int, rng: np.random.Generator | None, scale: tuple[float, float] = (0.6, 1.4),
          min_visible: float = 0.3) -> Sample:
    """The sample on a ``size`` x ``size`` grey canvas. With ``rng``: random scale (around "longer side = size")
    and position, flip, HSV jitter; boxes cut by the canvas keep only if ``min_visible`` of their area is left.
    Without ``rng``: plain letterbox (evaluation)."""
    img, boxes = sample.image, sample.boxes.astype(np.float64).copy()
    h, w = img.shape[:2]
    r = size / max(h, w) * (rng.uniform(*scale) if rng is not None else 1.0)
    nw, nh = max(1, round(w * r)), max(1, round(h * r))
    im = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_LINEAR)
    if rng is not None:
        ox, oy = rng.integers(min(0, size - nw), max(0, size - nw) + 1), rng.integers(min(0, size - nh), max(0, size - nh) + 1)
    else:
        ox, oy = (size - nw) // 2, (size - nh) // 2
    canvas = np.full((size, size, 3), 114, np.uint8)
    x0, y0, x1, y1 = max(ox, 0), max(oy, 0), min(ox + nw, size), min(oy + nh, size)
    canvas[y0:y1, x0:x1] = im[y0 - oy:y1 - oy, x0 - ox:x1 - ox]
    b = boxes * r + [ox, oy, ox, oy]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    b = np.clip(b, 0, size)
    keep = ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) >= min_visible * np.maximum(area, 1e-9)) & (b[:, 2] - b[:, 0] > 2) & (b[:, 3] - b[:, 1] > 2)
    b, labels = b[keep], sample.labels[keep]
    if rng is not None:
        if rng.random() < 0.5:
            canvas = canvas[:, ::-1].copy()
            b = np.stack([size - b[:, 2], b[:, 1], size - b[:, 0], b[:, 3]], 1)
        canvas = _hsv_jitter(canvas, rng)
    return Sample(canvas, b.reshape(-1, 4), labels)


def collate(samples: list[Sample]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """-> images (B,3,S,S) float32 RGB in [0,1], boxes (B,M,4), labels (B,M), mask (B,M) (padded to the max M)."""
    imgs, boxes, labels, mask = collate_u8(samples)
    return imgs.astype(np.float32) / 255.0, boxes, labels, mask


def collate_u8(samples: list[Sample]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``collate`` with the images left uint8 (B,3,S,S) RGB: a quarter of the bytes to move between processes
    or to a GPU; ``x.float() / 255`` there gives ``collate``'s values exactly."""
    m = max([len(s.boxes) for s in samples] + [1])
    B = len(samples)
    boxes, labels, mask = np.zeros((B, m, 4), np.float32), np.zeros((B, m), np.int64), np.zeros((B, m), bool)
    for i, s in enumerate(samples):
        k = len(s.boxes)
        boxes[i, :k], labels[i, :k], mask[i, :k] = s.boxes, s.labels, True
    imgs = np.ascontiguousarray(np.stack([s.image[..., ::-1] for s in samples]).transpose(0, 3, 1, 2))
    return imgs, boxes, labels, mask
