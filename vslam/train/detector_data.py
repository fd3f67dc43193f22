"""Detector training data: YOLO-format folders (COCO128) and synthetic frames with their exact mover boxes.

A sample is (image (H,W,3) uint8 BGR, boxes (K,4) float x1,y1,x2,y2 pixels, labels (K,) int into the training
class list), optionally with instance masks for the mask head (``Sample``). Augmentation (random scale /
placement on a square canvas, horizontal flip, HSV jitter) draws from the ``np.random.Generator`` it is given,
so a run is reproducible and resumable per iteration; masks and ignore regions follow the image without a draw
of their own, so a recipe gives the same images and boxes with or without them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vslam.dynamic.masking import box_iou
from vslam.errors import DatasetError

log = logging.getLogger(__name__)


# COCO category id (as in COCO's JSON and in COCO128's ``segments/``) of each of the 80 classes of ``labels/``
COCO80_TO_91 = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 27, 28, 31,
                32, 33, 34, 35, 36, 37, 38, 39, 40, 41, 42, 43, 44, 46, 47, 48, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58,
                59, 60, 61, 62, 63, 64, 65, 67, 70, 72, 73, 74, 75, 76, 77, 78, 79, 80, 81, 82, 84, 85, 86, 87, 88, 89,
                90)


@dataclass
class Sample:
    """One training image. image: (H,W,3) uint8 BGR; boxes: (K,4) float x1,y1,x2,y2 pixels; labels: (K,) int into
    the training class list. For the mask head, optionally: masks (K,H,W) bool aligned with boxes (None: no
    instance has one); mask_valid (K,) bool, False where an instance has a box but no mask (a KITTI or teacher
    box, a synthetic mover overlapped by another; None: all valid when masks is given, none otherwise); ignore
    (J,4) regions left out of the loss (KITTI DontCare). ``mask_validity`` / ``instance_masks`` / ``ignore_boxes``
    read these with the defaults filled in."""

    image: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    masks: np.ndarray | None = None
    mask_valid: np.ndarray | None = None
    ignore: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.boxes)
        if self.masks is not None and (self.masks.dtype != bool or self.masks.shape != (k, *self.image.shape[:2])):
            raise ValueError(f"Sample.masks must be ({k}, {self.image.shape[0]}, {self.image.shape[1]}) bool, "
                             f"got {self.masks.shape} {self.masks.dtype}")
        if self.mask_valid is not None and self.mask_valid.shape != (k,):
            raise ValueError(f"Sample.mask_valid must be ({k},), got {self.mask_valid.shape}")
        if self.ignore is not None and (self.ignore.ndim != 2 or self.ignore.shape[1] != 4):
            raise ValueError(f"Sample.ignore must be (J, 4), got {self.ignore.shape}")


def mask_validity(s: Sample) -> np.ndarray:
    """(K,) bool: which instances of ``s`` have a mask."""
    if s.mask_valid is not None:
        return s.mask_valid.astype(bool)
    return np.full(len(s.boxes), s.masks is not None)


def instance_masks(s: Sample) -> np.ndarray:
    """(K,H,W) bool, all False for a sample without masks."""
    return s.masks if s.masks is not None else np.zeros((len(s.boxes), *s.image.shape[:2]), bool)


def ignore_boxes(s: Sample) -> np.ndarray:
    """(J,4) float64 ignore regions, (0,4) for a sample without any."""
    return np.zeros((0, 4)) if s.ignore is None else s.ignore.astype(np.float64).reshape(-1, 4)


def add_instances(s: Sample, boxes: np.ndarray, labels: np.ndarray, masks: np.ndarray | None = None,
                  valid: np.ndarray | None = None) -> Sample:
    """``s`` with instances appended: boxes (N,4), labels (N,), masks (N,H,W) bool or None (no mask), valid (N,)
    (default: True where ``masks`` is given). A sample and additions without masks stay without (no (K,H,W)
    array of zeros is made)."""
    boxes, labels = np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(labels, np.int64).reshape(-1)
    n = len(boxes)
    if valid is None:
        valid = np.full(n, masks is not None)
    all_boxes = np.concatenate([s.boxes.reshape(-1, 4).astype(np.float64), boxes])
    all_labels = np.concatenate([s.labels.astype(np.int64), labels])
    all_valid = np.concatenate([mask_validity(s), valid.astype(bool)])
    if s.masks is None and masks is None:
        return Sample(s.image, all_boxes, all_labels, None, all_valid, s.ignore)
    new = masks if masks is not None else np.zeros((n, *s.image.shape[:2]), bool)
    return Sample(s.image, all_boxes, all_labels, np.concatenate([instance_masks(s), new]), all_valid, s.ignore)


def resize_masks(masks: np.ndarray, width: int, height: int) -> np.ndarray:
    """(K,H,W) bool -> (K,height,width) bool: area-averaged when shrinking, bilinear when growing, then > 0.5 (a
    mask pixel is on where most of it was)."""
    if masks.shape[1:] == (height, width):
        return masks.copy()
    shrink = width * height < masks.shape[1] * masks.shape[2]
    interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    out = np.empty((len(masks), height, width), bool)
    for i, m in enumerate(masks):  # one channel at a time: no (H,W,K) transpose to copy
        out[i] = cv2.resize(m.view(np.uint8) * np.uint8(255), (width, height), interpolation=interp) > 127
    return out


def polygon_mask(poly: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,2) vertices in pixels -> (height,width) bool of the filled polygon. Vertices are taken as pixel indices
    (cv2.fillPoly with 1/16 px precision), as ``composite.person_instances`` draws COCO polygons: the filled
    area then spans COCO's box of the instance to within 2 px for most instances (docs/detector-data.md)."""
    m = np.zeros((height, width), np.uint8)
    cv2.fillPoly(m, [np.round(np.asarray(poly, np.float64) * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def _read_names(root: Path) -> list[str]:
    import yaml

    path = root / "names.yaml"
    if not path.is_file():
        raise DatasetError(path, "missing (a YOLO dataset needs names.yaml)")
    names = yaml.safe_load(path.read_text())["names"]
    return [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)


def load_yolo(root: str | Path, split: str, classes: tuple[str, ...], max_side: int = 640,
              skip: frozenset[str] = frozenset(), segments: bool = False) -> list[Sample]:
    """``root/images/<split>/*.jpg`` with ``root/labels/<split>/*.txt`` (class cx cy w h, normalised).
    Boxes of classes not in ``classes`` are dropped; images are downscaled so the longer side is ``max_side``;
    images whose stem is in ``skip`` are left out. ``segments``: instance masks from the polygons of
    ``root/segments/<split>/`` (``yolo_polygons``), matched to the boxes by class and box (``match_polygons``);
    a box without a polygon (a crowd box, an image without a segments file) has ``mask_valid`` False."""
    root = Path(root)
    names = _read_names(root)
    to_ours = {i: classes.index(n) for i, n in enumerate(names) if n in classes}
    seg_dir = root / "segments" / split
    if segments and not seg_dir.is_dir():
        raise DatasetError(seg_dir, "missing (load_yolo(segments=True) needs the instance polygons)")
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
        sample = Sample(img, boxes.reshape(-1, 4), labels)
        if segments:
            sample = _with_polygons(sample, rows[:, 0].astype(np.int64), seg_dir / (img_path.stem + ".txt"),
                                    w * r, h * r)
        out.append(sample)
    if not out:
        raise DatasetError(root / "images" / split, "no images")
    return out


def yolo_polygons(path: Path) -> list[tuple[int, np.ndarray]]:
    """A YOLO-seg file (``class x1 y1 x2 y2 ...``, normalised, one instance a line) -> (class, (N,2) vertices).
    COCO128's ``segments/`` give the COCO category id (1 = person), not the 80-class index of ``labels/``, and do
    not follow the order of ``labels/`` (docs/detector-data.md)."""
    out = []
    for ln, text in enumerate(path.read_text().splitlines(), 1):
        if not text.strip():
            continue
        try:
            v = [float(x) for x in text.split()]
        except ValueError:
            v = []
        if len(v) < 7 or len(v) % 2 == 0 or not all(np.isfinite(v)) or v[0] != int(v[0]):
            raise DatasetError(path, f"a segment row is 'class x1 y1 x2 y2 x3 y3 ...' (3+ normalised vertices), "
                                     f"got {text.strip()[:60]!r}", ln)
        out.append((int(v[0]), np.array(v[1:], np.float64).reshape(-1, 2)))
    return out


def match_polygons(boxes: np.ndarray, classes: np.ndarray, poly_boxes: np.ndarray, poly_classes: np.ndarray,
                   min_iou: float = 0.5) -> np.ndarray:
    """(K,) index of the polygon of each box, -1 for none: pairs of the same class, greedily by the IoU of the box
    with the polygon's bounding box, one polygon per box, IoU at least ``min_iou``."""
    out = np.full(len(boxes), -1, np.int64)
    if not len(boxes) or not len(poly_boxes):
        return out
    iou = box_iou(boxes, poly_boxes)
    iou[classes[:, None] != poly_classes[None, :]] = -1.0
    for flat in np.argsort(-iou, axis=None, kind="stable"):
        i, j = divmod(int(flat), iou.shape[1])
        if iou[i, j] < min_iou:
            break
        if out[i] < 0 and j not in out:
            out[i] = j
    return out


def _with_polygons(s: Sample, coco80: np.ndarray, seg_path: Path, width: float, height: float) -> Sample:
    """``s`` with the masks of the polygons in ``seg_path`` matched to its boxes (``coco80``: each box's class
    in ``labels/``); boxes without a polygon, or all of them when the file is missing, have no mask."""
    H, W = s.image.shape[:2]
    masks, valid = np.zeros((len(s.boxes), H, W), bool), np.zeros(len(s.boxes), bool)
    polys = yolo_polygons(seg_path) if seg_path.is_file() else []
    if polys and len(s.boxes):
        to80 = {c91: i for i, c91 in enumerate(COCO80_TO_91)}
        pts = [p * [width, height] for _, p in polys]
        pboxes = np.array([[*p.min(0), *p.max(0)] for p in pts])
        pcls = np.array([to80.get(c, -1) for c, _ in polys], np.int64)
        for i, j in enumerate(match_polygons(s.boxes, coco80, pboxes, pcls)):
            if j >= 0:
                masks[i] = polygon_mask(pts[j], W, H)
                valid[i] = masks[i].any()
    return Sample(s.image, s.boxes, s.labels, masks if valid.any() else None, valid, s.ignore)


def synthetic_samples(seeds: tuple[int, ...], n_frames: int, stride: int, person: int, n_movers: int = 6,
                      width: int = 640, height: int = 480, masks: bool = False) -> list[Sample]:
    """Frames of synthetic rooms with ``n_movers`` people-sized movers; their exact boxes labelled ``person``.
    Frames without a visible mover are kept too (negatives), every ``stride``-th frame. ``masks``: each mover's
    instance mask where the frame's mover mask separates it (``separate_movers``)."""
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

    out = []
    for seed in seeds:
        seq = SyntheticSequence(SyntheticConfig(n_frames=n_frames, seed=seed, n_movers=n_movers, width=width, height=height))
        for i, fr in enumerate(seq):
            if i % stride:
                continue
            boxes = np.zeros((0, 4)) if fr.boxes is None else np.asarray(fr.boxes, np.float64).reshape(-1, 4)
            big = ((boxes[:, 2] - boxes[:, 0]) > 4) & ((boxes[:, 3] - boxes[:, 1]) > 4)
            img = fr.image if fr.image.ndim == 3 else cv2.cvtColor(fr.image, cv2.COLOR_GRAY2BGR)
            s = Sample(img, boxes[big], np.full(int(big.sum()), person, np.int64))
            if masks:
                dyn = fr.dynamic_mask if fr.dynamic_mask is not None else np.zeros(img.shape[:2], bool)
                m, valid = separate_movers(dyn, boxes)  # every box: a small mover may overlap a big one
                s = Sample(s.image, s.boxes, s.labels, m[big] if valid[big].any() else None, valid[big])
            out.append(s)
    return out


def separate_movers(mask: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The union mask (H,W) bool of all movers and each mover's box (K,4, inclusive pixel bounds, as the synthetic
    renderer gives them) -> (masks (K,H,W) bool, valid (K,) bool). A mover's pixels all lie in its own box, so
    the mask pixels of box k outside every other box are mover k's: that is its mask, exact (valid) unless some
    mask pixel lies where box k overlaps another box (whose mover it is, the union cannot tell)."""
    H, W = mask.shape
    k = len(boxes)
    ib = np.round(boxes).astype(np.int64).reshape(-1, 4)
    x0, y0 = np.clip(ib[:, 0], 0, W), np.clip(ib[:, 1], 0, H)
    x1, y1 = np.clip(ib[:, 2] + 1, 0, W), np.clip(ib[:, 3] + 1, 0, H)
    count = np.zeros((H, W), np.int32)  # how many boxes cover each pixel
    for i in range(k):
        count[y0[i]:y1[i], x0[i]:x1[i]] += 1
    out, valid = np.zeros((k, H, W), bool), np.zeros(k, bool)
    for i in range(k):
        win, cnt = mask[y0[i]:y1[i], x0[i]:x1[i]], count[y0[i]:y1[i], x0[i]:x1[i]]
        out[i, y0[i]:y1[i], x0[i]:x1[i]] = win & (cnt == 1)
        valid[i] = not (win & (cnt > 1)).any() and bool(out[i].any())
    return out, valid


def _hsv_jitter(img: np.ndarray, rng: np.random.Generator, h: float = 0.015, s: float = 0.7, v: float = 0.4) -> np.ndarray:
    """Random gains on hue, saturation and value. Each output byte is a function of its input byte alone, so the
    float arithmetic runs once per possible value (a 256-entry table per channel, ``cv2.LUT``) instead of once
    per pixel: the same bytes as the per-pixel formula (``tests/train/test_detector.py``), 7.5x cheaper."""
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
    Without ``rng``: plain letterbox (evaluation). Masks (``resize_masks``) and ignore regions move with the
    image and draw nothing from ``rng``; a dropped box drops its mask."""
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
    flip = rng is not None and rng.random() < 0.5
    if flip:
        canvas = canvas[:, ::-1].copy()
        b = _mirrored(b, size)
    if rng is not None:
        canvas = _hsv_jitter(canvas, rng)
    masks, valid = _place_masks(sample, keep, nw, nh, ox, oy, size, flip)
    ignore = None
    if sample.ignore is not None:
        ignore = np.clip(ignore_boxes(sample) * r + [ox, oy, ox, oy], 0, size)
        ignore = ignore[(ignore[:, 2] > ignore[:, 0]) & (ignore[:, 3] > ignore[:, 1])]
        if flip:
            ignore = _mirrored(ignore, size)
    return Sample(canvas, b.reshape(-1, 4), labels, masks, valid, ignore)


def _mirrored(boxes: np.ndarray, size: int) -> np.ndarray:
    """(N,4) x1,y1,x2,y2 boxes of a ``size``-wide canvas flipped left-right."""
    return np.stack([size - boxes[:, 2], boxes[:, 1], size - boxes[:, 0], boxes[:, 3]], 1).reshape(-1, 4)


def _place_masks(sample: Sample, keep: np.ndarray, nw: int, nh: int, ox: int, oy: int, size: int,
                 flip: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``place``'s masks of the kept boxes: resized to nw x nh, put at (ox, oy) on the canvas, mirrored if
    ``flip``. An instance without a mask stays all False (nothing to resize)."""
    if sample.masks is None:
        return None, (sample.mask_valid[keep] if sample.mask_valid is not None else None)
    valid = mask_validity(sample)[keep]
    masks = np.zeros((len(valid), size, size), bool)
    x0, y0, x1, y1 = max(ox, 0), max(oy, 0), min(ox + nw, size), min(oy + nh, size)
    cols = slice(size - x1, size - x0) if flip else slice(x0, x1)
    for i, src in zip(np.flatnonzero(valid), np.flatnonzero(keep)[valid]):
        m = resize_masks(sample.masks[src][None], nw, nh)[0, y0 - oy:y1 - oy, x0 - ox:x1 - ox]
        masks[i, y0:y1, cols] = m[:, ::-1] if flip else m
    return masks, valid


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


def collate_masks(samples: list[Sample], stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """-> masks (B,M,S/stride,S/stride) float32 in [0,1], each the fraction of a stride x stride cell inside the
    instance (area downsampling), and valid (B,M) bool; slot m is box m of ``collate`` (padded to the same M).
    Padding and instances without a mask are zeros with valid False."""
    H, W = samples[0].image.shape[:2]
    if H % stride or W % stride:
        raise ValueError(f"collate_masks: image {W}x{H} is not a multiple of stride {stride}")
    m = max([len(s.boxes) for s in samples] + [1])
    gh, gw = H // stride, W // stride
    out, valid = np.zeros((len(samples), m, gh, gw), np.float32), np.zeros((len(samples), m), bool)
    for i, s in enumerate(samples):
        v = mask_validity(s)
        if s.masks is None or not v.any():
            continue
        for j in np.flatnonzero(v):  # INTER_AREA by a whole factor: the exact mean of each cell
            out[i, j] = cv2.resize(s.masks[j].view(np.uint8).astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
        valid[i, :len(v)] = v
    return out, valid


def collate_ignore(samples: list[Sample]) -> tuple[np.ndarray, np.ndarray]:
    """-> ignore regions (B,J,4) float32 x1,y1,x2,y2 pixels and mask (B,J) bool (padded to the max J, at least 1)."""
    j = max([len(ignore_boxes(s)) for s in samples] + [1])
    out, mask = np.zeros((len(samples), j, 4), np.float32), np.zeros((len(samples), j), bool)
    for i, s in enumerate(samples):
        g = ignore_boxes(s)
        out[i, :len(g)], mask[i, :len(g)] = g, True
    return out, mask
