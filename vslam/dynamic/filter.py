"""DynamicFilter: the one object SlamTracker talks to. Which keypoints of a frame may be tracked and mapped."""

from __future__ import annotations

import logging
from collections import deque

import cv2
import numpy as np

from vslam.data.types import Frame, PinholeCamera
from vslam.dynamic.config import DynamicConfig
from vslam.dynamic.masking import dilate, in_boxes, in_mask
from vslam.dynamic.motion import GeometricCheck
from vslam.features.base import Features

log = logging.getLogger(__name__)


class DynamicFilter:
    """Per frame: ``keep(frame, features)`` before tracking (masks/boxes of dynamic objects and the regions the
    geometric check flagged in the previous frame), then ``observe(T_world_cam)`` once the pose is tracked
    (geometric check; returns the kept keypoints that turned out to move, to be left out of mapping)."""

    def __init__(self, cfg: DynamicConfig, cam: PinholeCamera, detector: object | None = None):
        self.cfg, self.cam = cfg, cam
        self.geo = GeometricCheck(cfg.geometric, cam) if cfg.geometric.enabled else None
        self.detector = detector
        if cfg.source == "detector" and detector is None:
            from vslam.dynamic.detector import default_weights, load_detector

            self.detector = load_detector(cfg.weights or default_weights(), conf=cfg.score_threshold)
            if cfg.img_size:  # wide frames (KITTI 1226x370): people stay large enough at a larger input
                self.detector.img_size = cfg.img_size
        self._recent: deque[tuple[float, np.ndarray]] = deque()  # (timestamp, boxes) of this and recent frames
        self._feats: Features | None = None
        self._depth = np.zeros(0)
        self._kept = np.zeros(0, bool)

    def dynamic_source(self, frame: Frame, feats: Features) -> np.ndarray:
        """(N,) bool: keypoints on dynamic objects according to ``cfg.source`` (dilated by ``dilation_px``)."""
        c = self.cfg
        if c.source == "gt_mask":
            if frame.dynamic_mask is not None:
                return in_mask(feats.raw, dilate(frame.dynamic_mask, c.dilation_px))
            if frame.boxes is not None:
                return in_boxes(feats.raw, frame.boxes, c.dilation_px)
            return np.zeros(len(feats), bool)
        if c.source == "detector":
            det = self.detector.detect(frame.image)  # type: ignore[union-attr]
            sel = (det.scores >= c.score_threshold) & np.isin(det.class_names, list(c.classes))
            self._recent.append((frame.timestamp, det.boxes[sel]))
            while frame.timestamp - self._recent[0][0] > c.box_memory_s + 1e-6:
                self._recent.popleft()
            return in_boxes(feats.raw, np.concatenate([b for _, b in self._recent]), c.dilation_px, c.box_grow)
        return np.zeros(len(feats), bool)

    def keep(self, frame: Frame, feats: Features) -> np.ndarray:
        """(N,) bool over ``feats``: True for keypoints that may be used for tracking and mapping."""
        dyn = self.dynamic_source(frame, feats)
        self._feats = feats
        self._depth = self._keypoint_depth(frame, feats)
        if self.geo is not None:
            dyn |= self.geo.in_region(feats.uv, self._depth)
        self._kept = ~dyn
        return self._kept.copy()

    def observe(self, T_world_cam: np.ndarray, tracked: bool = True) -> np.ndarray:
        """After tracking the frame given to ``keep``: (M,) bool over its kept keypoints, True where the geometric
        check flags motion. An untracked frame resets the check (its pose is only a prediction)."""
        n_kept = int(self._kept.sum())
        if self.geo is None or self._feats is None:
            return np.zeros(n_kept, bool)
        if not tracked:
            self.geo.reset()
            return np.zeros(n_kept, bool)
        flagged = self.geo.check(T_world_cam, self._feats.uv, self._depth, self._feats.desc)
        return flagged[self._kept]

    def _keypoint_depth(self, frame: Frame, feats: Features) -> np.ndarray:
        """(N,) metres at each keypoint from the frame's depth map (RGB-D); NaN without one (the geometric check
        then has nothing to compare, stereo/mono are not covered yet)."""
        if frame.depth is None or self.geo is None:
            return np.full(len(feats), np.nan)
        g = self.cfg.geometric
        r = np.clip(np.rint(feats.raw[:, 1]).astype(int), 0, frame.depth.shape[0] - 1)
        c = np.clip(np.rint(feats.raw[:, 0]).astype(int), 0, frame.depth.shape[1] - 1)
        z = frame.depth[r, c].astype(np.float64)
        ok = (z >= g.min_depth) & (z <= g.max_depth)
        if g.edge_m > 0:  # on a depth edge the keypoint's depth may be the background's
            d = frame.depth.astype(np.float32)
            k = np.ones((5, 5), np.uint8)
            hi = cv2.dilate(d, k)  # holes (0) raise neither bound: Kinect holes are everywhere
            lo = cv2.erode(np.where(d > 0, d, np.float32(1e6)), k)
            ok &= (hi[r, c] - lo[r, c]) <= g.edge_m + g.rel * z
        return np.where(ok, z, np.nan)
