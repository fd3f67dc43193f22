"""Copy-paste augmentation: COCO person instances pasted onto the scenes SLAM runs in.

Dwibedi et al., "Cut, Paste and Learn", ICCV 2017, and Ghiasi et al., "Simple Copy-Paste is a Strong Data
Augmentation Method for Instance Segmentation", CVPR 2021: pasting segmented instances at random scales and
places onto other images is enough to teach a detector objects in scenes it has no labels for. Here the
backgrounds are the training frames of the real sequences we hold (TUM teddy, KITTI 07, EuRoC V1_01) and
COCO128 train images; the people come from COCO128 polygons, never from the images whose people walk through
the dynamic benchmark (``composite.benchmark_stems``), so the benchmark's walkers stay unseen.

A pasted person may be partly outside the canvas or hidden by a later paste; its box is the box of its visible
pixels, and it is dropped when less than ``min_visible`` of it is left. Sizes: a person 0.15-0.95 of the image
height, and with probability ``closeup`` 1-2 image heights, cut by the frame (someone walking past the camera:
the dynamic benchmark's walkers come that close, and a detector that never saw a torso without head and feet
misses them); brightness follows the background (gain 0.5-1.3) and the alpha edge is feathered by a 3x3 blur,
so the pasted outline is not a shortcut. Optionally a person leans (``tilt``) or is partly hidden behind a patch
of the scene (``occluded``): people lean in the image of a hand-held camera that rolls, and the benchmark's walkers
pass behind the teddy bear.

Instance masks: a pasted person's mask is its visible part (alpha at least half, less what later pastes and
patches cover), the pixels its box is the box of; the masks of the background's own instances lose the pixels
a paste or patch now covers.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vslam.train.detector_data import Sample, ignore_boxes, instance_masks, mask_validity


def background_files(root: Path, sources: dict[str, tuple[str, int, int]]) -> list[Path]:
    """``sources``: kind -> (folder under ``root``, number of leading frames used, stride). Missing folders are
    left out (a fresh clone without the data)."""
    from vslam.train.keypoint_data import sequence_frames

    out: list[Path] = []
    for kind, (rel, n, stride) in sources.items():
        if (root / rel).exists():
            out += sequence_frames(kind, root / rel)[:n:stride]
    return out


def read_background(path: Path, max_side: int = 640) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        return None
    r = min(1.0, max_side / max(img.shape[:2]))
    return cv2.resize(img, (round(img.shape[1] * r), round(img.shape[0] * r)), interpolation=cv2.INTER_AREA) if r < 1 else img


def crop_background(img: np.ndarray, rng: np.random.Generator, aspect: float = 4 / 3) -> np.ndarray:
    """A random window of at most ``aspect`` width / height (KITTI's 1226x370 frames become several views)."""
    h, w = img.shape[:2]
    cw = min(w, int(round(h * aspect)))
    x0 = int(rng.integers(0, w - cw + 1))
    return img[:, x0:x0 + cw]


def crop_sample(s: Sample, rng: np.random.Generator, aspect: float = 4 / 3, min_visible: float = 0.3) -> Sample:
    """``crop_background`` of a labelled sample (the same draw): boxes, masks and ignore regions cut to the window;
    a box keeps only if ``min_visible`` of it is left, as in ``data.place``."""
    h, w = s.image.shape[:2]
    cw = min(w, int(round(h * aspect)))
    x0 = int(rng.integers(0, w - cw + 1))
    b = s.boxes.astype(np.float64).reshape(-1, 4) - [x0, 0, x0, 0]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    b[:, [0, 2]] = np.clip(b[:, [0, 2]], 0, cw)
    keep = ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) >= min_visible * np.maximum(area, 1e-9)) & (b[:, 2] - b[:, 0] > 2)
    ign = None
    if s.ignore is not None:
        ign = ignore_boxes(s) - [x0, 0, x0, 0]
        ign[:, [0, 2]] = np.clip(ign[:, [0, 2]], 0, cw)
        ign = ign[ign[:, 2] > ign[:, 0]]
    masks = None if s.masks is None else np.ascontiguousarray(s.masks[keep][:, :, x0:x0 + cw])
    valid = None if s.mask_valid is None else s.mask_valid[keep]
    return Sample(s.image[:, x0:x0 + cw], b[keep], s.labels[keep], masks, valid, ign)


def tilted(cut: np.ndarray, degrees: float) -> np.ndarray:
    """A BGRA cutout rotated by ``degrees`` on a canvas grown to hold all of it (transparent corners)."""
    ch, cw = cut.shape[:2]
    M = cv2.getRotationMatrix2D((cw / 2, ch / 2), degrees, 1.0)
    c, s = abs(M[0, 0]), abs(M[0, 1])
    nw, nh = int(np.ceil(ch * s + cw * c - 1e-6)), int(np.ceil(ch * c + cw * s - 1e-6))
    M[0, 2] += nw / 2 - cw / 2
    M[1, 2] += nh / 2 - ch / 2
    return cv2.warpAffine(cut, M, (nw, nh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(0, 0, 0, 0))


def occlude(img: np.ndarray, scene: np.ndarray, owner: np.ndarray, box: tuple[int, int, int, int],
            rng: np.random.Generator) -> tuple[int, int, int, int] | None:
    """Cover 30-70 % of a pasted person (``box`` x0, y0, x1, y1 of its pasted pixels) with a patch of ``scene``
    (the background before any paste, so no piece of a person is copied unlabelled) from elsewhere, in place:
    from the left, the right or below, or a band through the middle (someone behind a teddy bear on a table
    shows two halves). Covered pixels belong to no paste (``owner`` -1). -> the covered window x0, y0, x1, y1,
    None when the patch came out too thin to draw."""
    H, W = img.shape[:2]
    X0, Y0, X1, Y1 = box
    bw, bh, f = X1 - X0, Y1 - Y0, rng.uniform(0.3, 0.7)
    side = int(rng.integers(4))
    if side == 0:
        x0, x1, y0, y1 = X0, X0 + round(f * bw), Y0, Y1
    elif side == 1:
        x0, x1, y0, y1 = X1 - round(f * bw), X1, Y0, Y1
    elif side == 2:
        x0, x1, y0, y1 = X0, X1, Y1 - round(f * bh), Y1
    else:
        w = max(1, round(f * bw * 0.7))
        x0 = X0 + int(rng.integers(0, max(1, bw - w + 1)))
        x1, y0, y1 = x0 + w, Y0 + int(rng.integers(0, max(1, bh // 3))), Y1
    # two pixels more where the patch meets the box's edge: the feathered (blurred, resized) outline shows there
    x0, y0 = max(0, x0 - 2 * (x0 == X0)), max(0, y0 - 2 * (y0 == Y0))
    x1, y1 = min(W, x1 + 2 * (x1 == X1)), min(H, y1 + 2 * (y1 == Y1))
    w, h = x1 - x0, y1 - y0
    if w < 2 or h < 2:
        return None
    sx, sy = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
    img[y0:y1, x0:x1] = scene[sy:sy + h, sx:sx + w]
    owner[y0:y1, x0:x1] = -1
    return x0, y0, x1, y1


def paste(sample: Sample, cutouts: list[np.ndarray], label: int, rng: np.random.Generator, n: int,
          height: tuple[float, float] = (0.15, 0.95), min_visible: float = 0.3, closeup: float = 0.0,
          closeup_height: tuple[float, float] = (1.0, 2.0), tilt: float = 0.0, tilt_deg: float = 25.0,
          occluded: float = 0.0) -> Sample:
    """``sample`` with ``n`` random cutouts (BGRA) pasted as class ``label``. Existing boxes are kept (a paste
    over a labelled object only hides part of it; a fully hidden one would still be labelled, which at our
    paste sizes is rare and matches COCO's own occluded labels). With probability ``tilt`` a cutout is rotated
    by up to ``tilt_deg`` (a billboard seen by a rolling camera leans), with probability ``occluded`` part of it
    is then covered (``occlude``). Probabilities at 0 draw nothing, so earlier recipes stay reproducible.
    Masks (module docstring): the result has masks when the background has or a person is pasted; the
    background's instances without a mask stay without (``mask_valid`` False), as does one a paste hides
    entirely."""
    img = sample.image.copy()
    H, W = img.shape[:2]
    owner = np.full((H, W), -1, np.int32)  # which paste is visible at each pixel
    covered = np.zeros((H, W), bool)  # pixels a paste or a patch drew over: hidden from the background's instances
    areas = []
    for k in range(n):
        cut = cutouts[int(rng.integers(len(cutouts)))]
        if tilt > 0 and rng.random() < tilt:
            cut = tilted(cut, rng.uniform(-tilt_deg, tilt_deg))
        ch, cw = cut.shape[:2]
        near = closeup > 0 and rng.random() < closeup  # no extra draw at 0: earlier recipes stay reproducible
        s = min(rng.uniform(*(closeup_height if near else height)) * H / ch, (2.0 if near else 1.0) * W / cw)
        nw, nh = max(2, round(cw * s)), max(2, round(ch * s))
        cut = cv2.resize(cut, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        if rng.random() < 0.5:
            cut = cut[:, ::-1]
        x0 = int(rng.integers(-nw // 3, W - 2 * nw // 3 + 1))
        y0 = int(rng.integers(-nh // 4, H - 3 * nh // 4 + 1))
        X0, Y0, X1, Y1 = max(x0, 0), max(y0, 0), min(x0 + nw, W), min(y0 + nh, H)
        if X1 - X0 < 2 or Y1 - Y0 < 2:
            continue
        part = cut[Y0 - y0:Y1 - y0, X0 - x0:X1 - x0]
        alpha = cv2.blur(part[..., 3].astype(np.float32) / 255.0, (3, 3))[..., None]
        colour = np.clip(part[..., :3].astype(np.float32) * rng.uniform(0.5, 1.3), 0, 255)
        region = img[Y0:Y1, X0:X1].astype(np.float32)
        img[Y0:Y1, X0:X1] = (alpha * colour + (1 - alpha) * region).astype(np.uint8)
        hard = part[..., 3] >= 128
        owner[Y0:Y1, X0:X1][hard] = k
        covered[Y0:Y1, X0:X1] |= hard
        areas.append((k, int(hard.sum()), (X0, Y0, X1, Y1)))
        if occluded > 0 and rng.random() < occluded:
            ys, xs = np.nonzero(owner[Y0:Y1, X0:X1] == k)
            if len(xs):
                box = (X0 + xs.min(), Y0 + ys.min(), X0 + xs.max() + 1, Y0 + ys.max() + 1)
                patch = occlude(img, sample.image, owner, box, rng)
                if patch is not None:
                    covered[patch[1]:patch[3], patch[0]:patch[2]] = True
    boxes, labels, masks = [sample.boxes.reshape(-1, 4)], [sample.labels], []
    for k, area, (X0, Y0, X1, Y1) in areas:
        ys, xs = np.nonzero(owner[Y0:Y1, X0:X1] == k)  # a paste owns pixels of its own window only
        if area == 0 or len(xs) < min_visible * area:
            continue
        boxes.append(np.array([[X0 + xs.min(), Y0 + ys.min(), X0 + xs.max() + 1, Y0 + ys.max() + 1]], np.float64))
        labels.append(np.array([label], np.int64))
        m = np.zeros((H, W), bool)
        m[Y0:Y1, X0:X1] = owner[Y0:Y1, X0:X1] == k
        masks.append(m)
    ignore = None if sample.ignore is None else ignore_boxes(sample)
    boxes_out, labels_out = np.concatenate(boxes).astype(np.float64), np.concatenate(labels)
    if sample.masks is None and not masks:
        return Sample(img, boxes_out, labels_out, None, sample.mask_valid, ignore)
    old, old_valid = instance_masks(sample) & ~covered, mask_validity(sample)
    old_valid = old_valid & old.any(axis=(1, 2))  # wholly hidden: no mask to learn
    all_masks = np.concatenate([old, np.array(masks, bool).reshape(-1, H, W)])
    return Sample(img, boxes_out, labels_out, all_masks, np.concatenate([old_valid, np.ones(len(masks), bool)]), ignore)
