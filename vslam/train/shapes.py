"""Synthetic shapes with exactly known corners: ConvPoint's first training stage ("MagicPoint", SuperPoint §4).

Each image is a smooth noisy background with filled polygons, line segments, stars, a warped checkerboard and
corner-free ellipses drawn over each other. The label of every shape is its set of geometric corners (polygon
vertices, segment ends, star centres and tips, checkerboard vertices); a corner covered by a later shape is
removed, so labels are what is visible. Drawn with OpenCV (its cost per image: docs/speed.md,
'Small exact speed-ups quoted in code comments'), seeded by the caller's generator.
"""

from __future__ import annotations

import cv2
import numpy as np


def _contrast_color(rng: np.random.Generator, under: float) -> float:
    """A grey at least 40 levels from ``under`` (the mean intensity the shape covers)."""
    for _ in range(10):
        c = float(rng.uniform(0, 255))
        if abs(c - under) >= 40:
            return c
    return 255.0 - under if under < 128 else 0.0


def _background(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    img = np.full((h, w), rng.uniform(0, 255), np.float32)
    noise = cv2.resize(rng.uniform(-1, 1, (max(2, h // 16), max(2, w // 16))).astype(np.float32), (w, h),
                       interpolation=cv2.INTER_CUBIC)
    return img + noise * rng.uniform(0, 40)


def _polygon(rng, h, w):
    c = rng.uniform([0.1 * w, 0.1 * h], [0.9 * w, 0.9 * h])
    r = rng.uniform(0.08, 0.3) * min(h, w)
    n = int(rng.integers(3, 7))
    for _ in range(20):  # star-shaped w.r.t. the centre, so the polygon is simple; reject flat corners
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        if np.min(np.diff(np.r_[ang, ang[0] + 2 * np.pi])) > 0.5:
            break
    pts = c + (r * rng.uniform(0.5, 1.0, n))[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    return "fill", [pts], pts


def _segments(rng, h, w):
    n = int(rng.integers(1, 4))
    segs = []
    for _ in range(n):
        a = rng.uniform([0, 0], [w, h])
        ang = rng.uniform(0, np.pi)
        length = rng.uniform(0.15, 0.5) * min(h, w)
        segs.append(np.stack([a, a + length * np.array([np.cos(ang), np.sin(ang)])]))
    return "lines", segs, np.concatenate(segs)


def _star(rng, h, w):
    c = rng.uniform([0.15 * w, 0.15 * h], [0.85 * w, 0.85 * h])
    n = int(rng.integers(3, 6))
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    if np.min(np.diff(np.r_[ang, ang[0] + 2 * np.pi])) < 0.4:
        ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 1)
    tips = c + (rng.uniform(0.1, 0.3, n) * min(h, w))[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    return "lines", [np.stack([c, t]) for t in tips], np.vstack([c[None], tips])


def _checkerboard(rng, h, w):
    rows, cols = int(rng.integers(3, 7)), int(rng.integers(3, 7))
    s = rng.uniform(0.08, 0.2) * min(h, w)
    gx, gy = np.meshgrid(np.arange(cols + 1) * s, np.arange(rows + 1) * s)
    grid = np.stack([gx, gy], axis=-1).reshape(-1, 2)
    src = np.float32([[0, 0], [cols * s, 0], [cols * s, rows * s], [0, rows * s]])
    c = rng.uniform([0.2 * w, 0.2 * h], [0.8 * w, 0.8 * h])
    ang = rng.uniform(0, np.pi)
    R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    dst = (src - src.mean(axis=0)) @ R.T + c + rng.normal(0, 0.06 * cols * s, (4, 2))
    H = cv2.getPerspectiveTransform(src, dst.astype(np.float32))
    pts = cv2.perspectiveTransform(grid[None].astype(np.float64), H)[0].reshape(rows + 1, cols + 1, 2)
    squares = [np.stack([pts[i, j], pts[i, j + 1], pts[i + 1, j + 1], pts[i + 1, j]])
               for i in range(rows) for j in range(cols) if (i + j) % 2 == 0]
    return "checker", squares, pts.reshape(-1, 2)


def _ellipse(rng, h, w):
    c = rng.uniform([0, 0], [w, h])
    axes = rng.uniform(0.05, 0.25, 2) * min(h, w)
    return "ellipse", [(c, axes, float(rng.uniform(0, 180)))], np.zeros((0, 2))


_KINDS = (_polygon, _polygon, _segments, _star, _checkerboard, _ellipse)


def render_shapes(rng: np.random.Generator, h: int = 120, w: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """One image -> (uint8 (h,w) grey, (N,2) float64 visible corner pixels inside the image)."""
    img = _background(rng, h, w)
    corners = np.zeros((0, 2))
    for _ in range(int(rng.integers(2, 7))):
        kind, parts, pts = _KINDS[int(rng.integers(len(_KINDS)))](rng, h, w)
        mask = np.zeros((h, w), np.uint8)
        if kind in ("fill", "checker"):
            cv2.fillPoly(mask, [np.round(p * 16).astype(np.int32) for p in parts], 255, cv2.LINE_8, shift=4)
            if kind == "checker":  # the board's white squares too: its outline covers what lies below
                hull = cv2.convexHull(np.round(pts * 16).astype(np.int32))
                board = np.zeros_like(mask)
                cv2.fillConvexPoly(board, hull, 255, cv2.LINE_8, shift=4)
        elif kind == "lines":
            th = int(rng.integers(1, 4))
            for p in parts:
                cv2.line(mask, tuple(np.round(p[0] * 16).astype(int)), tuple(np.round(p[1] * 16).astype(int)), 255, th,
                         cv2.LINE_8, shift=4)
        else:
            (c, ax, ang), = parts
            cv2.ellipse(mask, (int(c[0]), int(c[1])), (int(ax[0]), int(ax[1])), ang, 0, 360, 255, -1)
        m = mask > 0
        if not m.any():
            continue
        cover = board > 0 if kind == "checker" else m
        if kind == "checker":
            under = float(img[cover].mean())
            img[cover] = _contrast_color(rng, under)
            img[m] = _contrast_color(rng, float(img[cover].mean()))
        else:
            img[m] = _contrast_color(rng, float(img[m].mean()))
        if len(corners):  # corners now hidden by this shape are no longer visible
            grow = cv2.dilate(cover.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            ij = np.clip(np.round(corners).astype(np.int64), 0, [w - 1, h - 1])
            corners = corners[~grow[ij[:, 1], ij[:, 0]]]
        inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
        corners = np.vstack([corners, pts[inside]])
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 1.0))
    img = img + rng.normal(0, rng.uniform(0, 8), img.shape)
    return np.clip(img, 0, 255).astype(np.uint8), corners
