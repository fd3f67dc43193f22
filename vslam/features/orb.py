"""ORB (OpenCV) keypoints, bucketed over an image grid.

OpenCV's ORB keeps the strongest FAST corners per pyramid level, so a few
texture-rich regions can take nearly all of them and the pose becomes poorly
conditioned. We over-detect, then keep keypoints round-robin over grid cells
(rank within its cell first, response second) — the same intent as
ORB-SLAM's quadtree distribution, in a few vectorised lines.
"""

from __future__ import annotations

import cv2
import numpy as np

from vslam.data.types import PinholeCamera
from vslam.features.base import FeatureConfig, Features


def _gray(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def bucket(xy: np.ndarray, response: np.ndarray, shape: tuple[int, int], n: int, cols: int, rows: int) -> np.ndarray:
    """Indices of at most ``n`` keypoints spread over a cols x rows grid.

    xy: (N,2) pixels; shape: (H, W). Each cell contributes its best keypoint before
    any cell contributes its second, and so on; ties by response then index (deterministic).
    """
    if len(xy) <= n:
        return np.arange(len(xy))
    h, w = shape
    cx = np.clip((xy[:, 0] * cols / w).astype(np.int64), 0, cols - 1)
    cy = np.clip((xy[:, 1] * rows / h).astype(np.int64), 0, rows - 1)
    cell = cy * cols + cx
    m = len(xy)
    strength = np.empty(m, np.int64)  # 0 = strongest; equal responses by index
    strength[np.argsort(-response, kind="stable")] = np.arange(m)
    order = np.argsort(cell * m + strength)  # by cell, then strongest first (unique keys: one sort)
    sorted_cell = cell[order]
    first = np.r_[0, np.flatnonzero(np.diff(sorted_cell)) + 1]
    start = np.repeat(first, np.diff(np.r_[first, m]))
    rank = np.empty(m, np.int64)
    rank[order] = np.arange(m) - start
    pick = np.argpartition(rank * m + strength, n - 1)[:n]  # the n smallest (rank, strength) keys
    return np.sort(pick)


def orb_detector(cfg: FeatureConfig, nfeatures: int, fast_threshold: int) -> cv2.ORB:
    """OpenCV ORB with the project's pyramid and patch settings (extractor passes, vocabulary training)."""
    return cv2.ORB_create(nfeatures=nfeatures, scaleFactor=cfg.scale_factor, nlevels=cfg.n_levels, edgeThreshold=19,
                          patchSize=31, fastThreshold=fast_threshold)


class OrbExtractor:
    """ORB keypoints + 256-bit descriptors with grid bucketing."""

    descriptor_kind = "binary"

    def __init__(self, cfg: FeatureConfig = FeatureConfig()):
        self.cfg = cfg
        n = int(cfg.n_features * cfg.oversample)
        self.orb = orb_detector(cfg, n, cfg.fast_threshold)
        self.orb_low = None  # FeatureConfig.fast_threshold_min: the second pass on a poor image
        if 0 < cfg.fast_threshold_min < cfg.fast_threshold:
            self.orb_low = orb_detector(cfg, n, cfg.fast_threshold_min)

    def _dim(self, gray: np.ndarray) -> bool:
        """Low contrast (``FeatureConfig.low_contrast_spread``): few corners because the light is poor, not
        because the image is blurred or plain."""
        p5, p95 = np.percentile(gray[::4, ::4], [5, 95])
        return bool(p95 - p5 < self.cfg.low_contrast_spread)

    def detect(self, image: np.ndarray, camera: PinholeCamera, mask: np.ndarray | None = None) -> Features:
        gray = _gray(image)
        m = None if mask is None else (~mask).astype(np.uint8) * 255  # mask: True where features are NOT wanted
        kps = self.orb.detect(gray, m)
        if self.orb_low is not None and len(kps) < self.cfg.fast_retry_below * self.cfg.n_features and self._dim(gray):
            # every corner of the first pass passes the lower threshold too; the cap keeps the strongest
            kps = self.orb_low.detect(gray, m)
        empty = Features.empty(scale_factor=self.cfg.scale_factor)
        if not kps:
            return empty
        xy = cv2.KeyPoint_convert(kps).astype(np.float64)  # float32 -> float64: the same values as k.pt
        resp = np.array([k.response for k in kps], dtype=np.float64)
        keep = bucket(xy, resp, gray.shape[:2], self.cfg.n_features, self.cfg.grid_cols, self.cfg.grid_rows)
        kps, desc = self.orb.compute(gray, [kps[i] for i in keep])
        if desc is None or not kps:
            return empty
        raw = cv2.KeyPoint_convert(kps).astype(np.float64)
        return Features(
            raw=raw, uv=camera.undistort_points(raw), desc=desc,
            octave=np.array([k.octave for k in kps], dtype=np.int64),
            response=np.array([k.response for k in kps], dtype=np.float64),
            scale_factor=self.cfg.scale_factor,
        )
