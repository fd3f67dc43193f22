"""Random homographies and photometric changes: the pairs ConvPoint trains on and the feature benchmark scores.

A homography maps pixels of image A to image B (x_B ~ H x_A); B = ``warp(A, H)``. ``random_homography``
moves the four image corners by a random similarity (scale, rotation, shift) plus perspective jitter, then
checks the warped corners still form a convex quadrilateral, as SuperPoint's sampler does.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class HomographySpec:
    """Strength of a random homography; angles in degrees, the rest as fractions of the image size."""

    scale: tuple[float, float] = (0.75, 1.25)
    rotation_deg: float = 25.0
    perspective: float = 0.12  # corner jitter, fraction of the image size
    shift: float = 0.1


def random_homography(rng: np.random.Generator, h: int, w: int, spec: HomographySpec = HomographySpec()) -> np.ndarray:
    """(3,3) H: pixels of an h x w image -> pixels of its warped view (B's image keeps the size h x w)."""
    src = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    for _ in range(50):
        s = rng.uniform(*spec.scale)
        a = np.deg2rad(rng.uniform(-spec.rotation_deg, spec.rotation_deg))
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        dst = (src - c) @ R.T * s + c
        dst += rng.uniform(-spec.perspective, spec.perspective, (4, 2)) * [w, h]
        dst += rng.uniform(-spec.shift, spec.shift, 2) * [w, h]
        if cv2.isContourConvex(dst.astype(np.float32).reshape(-1, 1, 2)):
            break
    return cv2.getPerspectiveTransform(src, dst.astype(np.float32)).astype(np.float64)


def warp_points(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N,2) pixels through H (homogeneous division)."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    return p[:, :2] / p[:, 2:3]


def warp(image: np.ndarray, H: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """Image B = A seen through H (bilinear; outside A is black). size: (w, h) of B, default A's."""
    h, w = image.shape[:2]
    return cv2.warpPerspective(image, H, size or (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def valid_mask(H: np.ndarray, h: int, w: int, erode: int = 0) -> np.ndarray:
    """(h,w) bool: pixels of B that see A (optionally eroded by ``erode`` pixels)."""
    m = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h), flags=cv2.INTER_NEAREST)
    if erode > 0:
        m = cv2.erode(m, np.ones((2 * erode + 1, 2 * erode + 1), np.uint8))
    return m > 0


def inside(xy: np.ndarray, h: int, w: int, border: float = 0.0) -> np.ndarray:
    return (xy[:, 0] >= border) & (xy[:, 0] <= w - 1 - border) & (xy[:, 1] >= border) & (xy[:, 1] <= h - 1 - border)


def _shadow(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A multiplicative (h,w) field with 1-3 soft-edged dark or bright ellipses."""
    m = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 4))):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        ax = (int(rng.uniform(0.1, 0.5) * w), int(rng.uniform(0.1, 0.5) * h))
        cv2.ellipse(m, c, ax, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(-0.6, 0.4)), -1)
    k = max(3, int(0.1 * min(h, w)) | 1)
    return 1.0 + cv2.GaussianBlur(m, (k, k), 0)


def photometric(image: np.ndarray, rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Training augmentation of a grey uint8 image: gain, offset, gamma, shadows, noise, blur."""
    x = image.astype(np.float32) / 255.0
    x = x * rng.uniform(1 - 0.5 * strength, 1 + 0.5 * strength) + rng.uniform(-0.15, 0.15) * strength
    x = np.clip(x, 0, 1) ** rng.uniform(1 - 0.4 * strength, 1 + 0.7 * strength)
    if rng.random() < 0.5 * strength:
        x = x * _shadow(rng, *x.shape)
    x = x + rng.normal(0, rng.uniform(0, 0.03 * strength), x.shape)
    out = (np.clip(x, 0, 1) * 255).astype(np.uint8)
    if rng.random() < 0.3 * strength:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.3, 1.3))
    if rng.random() < 0.15 * strength:  # motion blur
        k = int(rng.integers(3, 8))
        kern = np.zeros((k, k), np.float32)
        kern[k // 2] = 1.0 / k
        kern = cv2.warpAffine(kern, cv2.getRotationMatrix2D(((k - 1) / 2, (k - 1) / 2), float(rng.uniform(0, 180)), 1.0), (k, k))
        out = cv2.filter2D(out, -1, kern / max(kern.sum(), 1e-6))
    return out


def illumination_change(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The benchmark's lighting change (stronger than training's mean): a global gain in [0.4, 0.7] or
    [1.4, 1.9], a gamma in [0.5, 0.7] or [1.5, 2.0], a soft shadow and sensor noise."""
    x = image.astype(np.float32) / 255.0
    gain = rng.uniform(0.4, 0.7) if rng.random() < 0.5 else rng.uniform(1.4, 1.9)
    gamma = rng.uniform(0.5, 0.7) if rng.random() < 0.5 else rng.uniform(1.5, 2.0)
    x = (np.clip(x * gain, 0, 1) ** gamma) * _shadow(rng, *x.shape)
    x = x + rng.normal(0, 0.01, x.shape)
    return (np.clip(x, 0, 1) * 255).astype(np.uint8)
