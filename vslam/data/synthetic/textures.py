"""Seeded procedural textures for the synthetic scenes.

A texture patch covers a rectangle of a face at ``ppm`` texels per metre;
texel (row i, col j) covers s in [j, j+1)/ppm and r in [i, i+1)/ppm of the
face's 2-D coordinates (s, r), so its centre is ((j + 0.5)/ppm, (i + 0.5)/ppm).
The renderer samples with that convention, which is what makes the
projection of a marker centre land on its rendered blob.

Textures are built for ORB-style detectors: high-contrast rectangles,
polygons and discs at several scales over multi-scale noise give hundreds
of corners per view; ``flat`` faces are nearly uniform with a few features.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MarkerStyle:
    """Black disc of radius r_in on a white disc of radius r_out (metres), on a jittered grid."""

    r_in: float
    r_out: float
    spacing: float


def _noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """(h,w) float32 smooth noise in [-1, 1] with features about ``cell`` texels wide."""
    small = rng.uniform(-1.0, 1.0, (max(2, h // cell + 2), max(2, w // cell + 2))).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _background(rng: np.random.Generator, h: int, w: int, base: np.ndarray, amp: float) -> np.ndarray:
    """Base colour plus tinted noise at three scales, uint8 (h,w,3)."""
    lum = np.zeros((h, w), np.float32)
    for cell, a in ((max(h, w) // 4 + 1, 0.5), (40, 0.3), (6, 0.2)):
        lum += np.float32(amp * a) * _noise(rng, h, w, cell)
    tint = rng.uniform(0.6, 1.0, 3)
    # base + tint * lum per channel, saturated to uint8 by OpenCV (numpy broadcasting is much slower here).
    chans = [cv2.addWeighted(lum, float(tint[c]), lum, 0.0, float(base[c]), dtype=cv2.CV_8U) for c in range(3)]
    return cv2.merge(chans)


def _colours(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,3) int BGR colours, each either dark or bright on average so neighbouring shapes contrast."""
    level = np.where(rng.uniform(size=n) < 0.5, rng.uniform(10, 90, n), rng.uniform(160, 250, n))
    return np.clip(level[:, None] + rng.uniform(-60, 60, (n, 3)), 0, 255).astype(int)


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    b, g, r = _colours(rng, 1)[0]
    return int(b), int(g), int(r)


def _shapes(rng: np.random.Generator, img: np.ndarray, ppm: float, n: int, size_m: tuple[float, float]) -> None:
    """Draw n random filled rectangles, discs and quadrilaterals (sizes log-uniform in size_m metres) in place."""
    h, w = img.shape[:2]
    sizes = np.exp(rng.uniform(np.log(size_m[0]), np.log(size_m[1]), n)) * ppm
    kinds = rng.integers(0, 3, n)
    centres = rng.uniform((0, 0), (w, h), (n, 2))
    colours = _colours(rng, n).tolist()
    extents = sizes[:, None] * rng.uniform(0.3, 1.0, (n, 4))  # rectangle half sizes or polygon radii
    angles = np.sort(rng.uniform(0, 2 * np.pi, (n, 4)), axis=1)
    for k, s, (x, y), col, ext, ang in zip(kinds, sizes, centres, colours, extents, angles):
        if k == 0:
            cv2.rectangle(img, (int(x - ext[0]), int(y - ext[1])), (int(x + ext[0]), int(y + ext[1])), col, -1)
        elif k == 1:
            cv2.circle(img, (int(x), int(y)), max(1, int(s * 0.5)), col, -1, cv2.LINE_AA)
        else:
            pts = np.stack([x + ext * np.cos(ang), y + ext * np.sin(ang)], axis=1).astype(np.int32)
            cv2.fillConvexPoly(img, pts, col, cv2.LINE_AA)


def rich(rng: np.random.Generator, h: int, w: int, ppm: float, density: float = 25.0) -> np.ndarray:
    """Busy texture: noisy background plus ``density`` shapes per square metre from 3 to 40 cm."""
    img = _background(rng, h, w, rng.uniform(60, 200, 3).astype(np.float32), 70.0)
    area = h * w / ppm**2
    _shapes(rng, img, ppm, int(area * density), (0.03, 0.4))
    _shapes(rng, img, ppm, int(area * density * 0.6), (0.015, 0.05))
    return img


def flat(rng: np.random.Generator, h: int, w: int, ppm: float, n_features: int = 4) -> np.ndarray:
    """Nearly uniform paint (+-2 grey levels) with a handful of shapes."""
    img = _background(rng, h, w, rng.uniform(120, 200, 3).astype(np.float32), 3.0)
    _shapes(rng, img, ppm, n_features, (0.1, 0.4))
    return img


def facade(rng: np.random.Generator, h: int, w: int, ppm: float, low_texture: bool) -> np.ndarray:
    """Building front: plaster or brick noise with a grid of framed windows (corners everywhere)."""
    if low_texture:
        return flat(rng, h, w, ppm, n_features=3)
    img = _background(rng, h, w, rng.uniform(70, 190, 3).astype(np.float32), 60.0)
    _shapes(rng, img, ppm, int(h * w / ppm**2 * 3), (0.1, 0.6))
    cols, rows = rng.integers(2, 5), max(2, int(h / ppm / 3.0))
    win_w, win_h = rng.uniform(0.8, 1.6) * ppm, rng.uniform(1.0, 1.6) * ppm
    for i in range(rows):
        for j in range(cols):
            x = (j + 0.5) * w / cols + rng.uniform(-0.2, 0.2) * ppm
            y = (i + 0.5) * h / rows
            p1 = (int(x - win_w / 2), int(y - win_h / 2))
            p2 = (int(x + win_w / 2), int(y + win_h / 2))
            cv2.rectangle(img, p1, p2, _colour(rng), -1)
            cv2.rectangle(img, p1, p2, (235, 235, 235), max(1, int(0.08 * ppm)))
            cv2.line(img, (int(x), p1[1]), (int(x), p2[1]), (235, 235, 235), max(1, int(0.05 * ppm)))
    return img


def ground(rng: np.random.Generator, h: int, w: int, ppm: float, low_texture: bool) -> np.ndarray:
    """Asphalt: grey noise, patches and dashed lane markings along s."""
    img = _background(rng, h, w, np.full(3, rng.uniform(70, 100), np.float32), 12.0 if low_texture else 45.0)
    _shapes(rng, img, ppm, 3 if low_texture else int(h * w / ppm**2 * 4), (0.05, 0.5))
    for y in (h // 2, int(h * 0.2), int(h * 0.8)):
        for x in np.arange(0, w, 6 * ppm):
            cv2.rectangle(img, (int(x), y - int(0.06 * ppm)), (int(x + 3 * ppm), y + int(0.06 * ppm)), (230, 230, 230), -1)
    return img


def sky(rng: np.random.Generator, h: int, w: int, ppm: float) -> np.ndarray:
    """Bright blue with soft clouds: few features, like a real sky."""
    base = np.array([235, 200, 150], np.float32)  # BGR light blue
    cloud = np.clip(_noise(rng, h, w, int(4 * ppm) + 1), 0, 1)[..., None]
    img = base * (1 - cloud) + np.float32(250) * cloud
    return np.clip(img, 0, 255).astype(np.uint8)


def mover(rng: np.random.Generator, h: int, w: int, ppm: float) -> np.ndarray:
    """Saturated clothing-like stripes and blobs, distinct from the walls."""
    img = np.empty((h, w, 3), np.uint8)
    img[:] = _colour(rng)
    y = 0.0
    while y < h:
        step = rng.uniform(0.05, 0.25) * ppm
        cv2.rectangle(img, (0, int(y)), (w, int(y + step)), _colour(rng), -1)
        y += step * rng.uniform(1.2, 2.5)
    _shapes(rng, img, ppm, max(4, int(h * w / ppm**2 * 30)), (0.02, 0.12))
    return img


def draw_markers(rng: np.random.Generator, img: np.ndarray, ppm: float, style: MarkerStyle) -> np.ndarray:
    """Paint markers on a jittered grid in place; returns their centres (M,2) in patch metres (s, r).

    Coverage is analytic (a one-texel linear ramp at each edge), so the
    rendered dark blob is symmetric about the true centre.
    """
    h, w = img.shape[:2]
    size = (w / ppm, h / ppm)
    margin = style.r_out + 2.0 / ppm
    centres = []
    for s0 in np.arange(style.spacing / 2, size[0], style.spacing):
        for r0 in np.arange(style.spacing / 2, size[1], style.spacing):
            jitter = rng.uniform(-0.25, 0.25, 2) * style.spacing
            s, r = s0 + jitter[0], r0 + jitter[1]
            if margin <= s <= size[0] - margin and margin <= r <= size[1] - margin:
                centres.append((s, r))
                _paint_marker(img, ppm, s, r, style)
    return np.array(centres, dtype=np.float64).reshape(-1, 2)


def _paint_marker(img: np.ndarray, ppm: float, s: float, r: float, style: MarkerStyle) -> None:
    j0, j1 = int((s - style.r_out) * ppm) - 1, int((s + style.r_out) * ppm) + 2
    i0, i1 = int((r - style.r_out) * ppm) - 1, int((r + style.r_out) * ppm) + 2
    jj, ii = np.meshgrid(np.arange(j0, j1), np.arange(i0, i1))
    d = np.hypot((jj + 0.5) / ppm - s, (ii + 0.5) / ppm - r) * ppm  # texels from the centre
    white = np.clip(style.r_out * ppm - d + 0.5, 0.0, 1.0)[..., None]
    black = np.clip(style.r_in * ppm - d + 0.5, 0.0, 1.0)[..., None]
    patch = img[i0:i1, j0:j1].astype(np.float32)
    patch = patch * (1 - white) + 255.0 * white
    patch = patch * (1 - black)
    img[i0:i1, j0:j1] = np.round(patch).astype(np.uint8)
