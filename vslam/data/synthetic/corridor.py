"""The "corridor" scene: a long, narrow, plain-painted hallway whose structure is edges, not corners.

Why: point features fail where line features still work (seed 003 ch. 3, Table 1: fr1_floor), and the
synthetic room's textures are built for corners. Here walls are near-uniform paint (the ``flat`` noise,
+-2 grey levels) carrying long straight edges: a dark baseboard and a chair rail along the whole length,
door frames with darker doors, and faint vertical panel seams; the floor has two long stripes and sparse
joints, the ceiling a row of light panels. Edges meet in few places (door corners, seam ends), so ORB
finds few stable corners, while LSD finds dozens of long segments per view.

Geometry: the box spans the camera path along +x with ``CORRIDOR_HALF_WIDTH`` either side and
``CORRIDOR_HEIGHT`` of ceiling; the camera walks straight down the middle (``motion._corridor_path``).
"""

from __future__ import annotations

import cv2
import numpy as np

from vslam.data.synthetic import textures

CORRIDOR_HALF_WIDTH = 1.3  # metres: walls at y = +-1.3
CORRIDOR_HEIGHT = 2.7
CORRIDOR_PPM = 150.0  # texels per metre


def corridor_box(cam_positions: np.ndarray, end: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) world corners of the corridor around the (N,2,3) camera centres; the end wall ``end`` metres
    beyond the last one."""
    x0, x1 = cam_positions[..., 0].min(), cam_positions[..., 0].max()
    return np.array([x0 - 6.0, -CORRIDOR_HALF_WIDTH, 0.0]), np.array([x1 + end, CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT])


def _line(img: np.ndarray, p1: tuple[float, float], p2: tuple[float, float], colour, width: float) -> None:
    cv2.line(img, (int(p1[0]), int(p1[1])), (int(p2[0]), int(p2[1])), colour, max(1, int(round(width))), cv2.LINE_AA)


def wall(rng: np.random.Generator, h: int, w: int, ppm: float) -> np.ndarray:
    """Wall texture (rows = height from the floor, s = along the corridor)."""
    img = textures.flat(rng, h, w, ppm, n_features=0)
    base = img.astype(np.float32).mean()
    dark = tuple(int(c) for c in np.clip(np.full(3, base - 90.0) + rng.uniform(-15, 15, 3), 0, 255))
    cv2.rectangle(img, (0, 0), (w, int(0.12 * ppm)), dark, -1)  # baseboard (row 0 = floor level)
    rail = int(0.95 * ppm)
    cv2.rectangle(img, (0, rail), (w, rail + int(0.06 * ppm)), dark, -1)  # chair rail
    x = rng.uniform(1.0, 3.0)
    while x < w / ppm - 1.5:  # doors every 3-6 m: frame + darker leaf
        x0, x1 = int(x * ppm), int((x + 0.9) * ppm)
        top = int(2.1 * ppm)
        leaf = tuple(int(c) for c in np.clip(np.full(3, base - 50.0) + rng.uniform(-30, 30, 3), 0, 255))
        cv2.rectangle(img, (x0, int(0.02 * ppm)), (x1, top), leaf, -1)
        cv2.rectangle(img, (x0, int(0.02 * ppm)), (x1, top), dark, max(1, int(0.05 * ppm)))
        x += rng.uniform(3.0, 6.0)
    seam = tuple(int(c) for c in np.clip(np.full(3, base - 25.0), 0, 255))
    for xs in np.arange(rng.uniform(0.3, 1.2), w / ppm, 1.2):  # panel seams between the rail and the ceiling
        _line(img, (xs * ppm, rail + 0.1 * ppm), (xs * ppm, h - 0.05 * ppm), seam, 0.015 * ppm)
    return img


def floor(rng: np.random.Generator, h: int, w: int, ppm: float) -> np.ndarray:
    """Floor: plain with two long stripes (rows = y across the corridor) and joints every 2.4 m."""
    img = textures.flat(rng, h, w, ppm, n_features=0)
    stripe = tuple(int(c) for c in rng.uniform(40, 90, 3))
    for r in (0.25, 0.75):
        y = int(r * h)
        cv2.rectangle(img, (0, y - int(0.04 * ppm)), (w, y + int(0.04 * ppm)), stripe, -1)
    joint = tuple(int(c) for c in np.clip(img.reshape(-1, 3).mean(axis=0) - 35.0, 0, 255))
    for xs in np.arange(rng.uniform(0.5, 2.0), w / ppm, 2.4):
        _line(img, (xs * ppm, 0), (xs * ppm, h), joint, 0.02 * ppm)
    return img


def ceiling(rng: np.random.Generator, h: int, w: int, ppm: float) -> np.ndarray:
    """Ceiling: plain with a row of bright light panels (0.6 x 1.2 m) every 3 m."""
    img = textures.flat(rng, h, w, ppm, n_features=0)
    for xs in np.arange(rng.uniform(0.5, 2.0), w / ppm - 1.2, 3.0):
        cv2.rectangle(img, (int(xs * ppm), int(h / 2 - 0.3 * ppm)), (int((xs + 1.2) * ppm), int(h / 2 + 0.3 * ppm)),
                      (250, 250, 250), -1)
    return img


def face_textures(rng: np.random.Generator, face_sizes: list[tuple[float, float]], ppm: float) -> list[np.ndarray]:
    """The six faces (f = 2 k + side, see scene.py): end walls plain, side walls, floor, ceiling."""
    out = []
    for f, (sw, sh) in enumerate(face_sizes):
        w, h = int(np.ceil(sw * ppm - 1e-6)), int(np.ceil(sh * ppm - 1e-6))
        if f in (2, 3):
            out.append(wall(rng, h, w, ppm))
        elif f == 4:
            out.append(floor(rng, h, w, ppm))
        elif f == 5:
            out.append(ceiling(rng, h, w, ppm))
        else:
            out.append(textures.flat(rng, h, w, ppm, n_features=2))
    return out
