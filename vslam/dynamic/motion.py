"""Geometric consistency check (DynaSLAM-style, no network): flag keypoints on things that move.

DynaSLAM (Bescos et al., RA-L 2018, Sec. III-C) projects keypoints of overlapping keyframes into the current
frame and calls a point dynamic when its measured depth disagrees with the projected one, then grows the
region in the depth image. Here the same test runs in 3-D and over several past frames: each keypoint's world
point (its depth back-projected with the tracked pose) is compared with the world point of the same feature
(descriptor match) ``g`` tracked frames back, for each gap ``g``. A static point agrees up to depth noise and
pose error; a point on a mover is off by the mover's displacement. Votes over several gaps make one bad match
or one noisy depth harmless, and a static instance of a "dynamic" class (a sitting person) is never flagged.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vslam.data.types import PinholeCamera
from vslam.dynamic.config import GeometricConfig


@dataclass
class _Past:
    Xw: np.ndarray  # (N,3) world points, NaN where the keypoint has no depth
    desc: np.ndarray  # (N,D)


class GeometricCheck:
    """``check(T_world_cam, uv, depth, desc)`` once per tracked frame -> flagged keypoints of that frame;
    ``in_region(uv, depth)`` says which keypoints of the *next* frame lie in the last flagged regions."""

    def __init__(self, cfg: GeometricConfig, cam: PinholeCamera):
        self.cfg, self.cam = cfg, cam
        self.history: deque[_Past] = deque(maxlen=max(cfg.frame_gaps))
        self._region_uv = np.zeros((0, 2))
        self._region_z = np.zeros(0)
        self.seeds = self.tested = np.zeros(0, bool)

    def reset(self) -> None:
        """Forget the past (after tracking loss the poses of old and new frames are not comparable)."""
        self.history.clear()
        self._region_uv, self._region_z = np.zeros((0, 2)), np.zeros(0)

    def _match(self, d1: np.ndarray, d2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mutual nearest descriptor matches (i in d1, j in d2) within the distance limit."""
        if len(d1) == 0 or len(d2) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        binary = d1.dtype == np.uint8
        norm, limit = (cv2.NORM_HAMMING, self.cfg.max_hamming) if binary else (cv2.NORM_L2, self.cfg.max_l2)
        a = d1 if binary else d1.astype(np.float32)
        b = d2 if binary else d2.astype(np.float32)
        ms = [m for m in cv2.BFMatcher(norm, crossCheck=True).match(a, b) if m.distance <= limit]
        return np.array([m.queryIdx for m in ms], np.int64), np.array([m.trainIdx for m in ms], np.int64)

    def residual_votes(self, Xw: np.ndarray, depth: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) number of past frames (of ``frame_gaps``) against which a keypoint's world point moved, and (N,)
        number it was compared with at all (matched, depth in both)."""
        c = self.cfg
        votes = np.zeros(len(Xw), np.int64)
        tested = np.zeros(len(Xw), np.int64)
        for g in c.frame_gaps:
            if len(self.history) < g:
                continue
            past = self.history[-g]
            i, j = self._match(desc, past.desc)
            ok = np.isfinite(Xw[i, 0]) & np.isfinite(past.Xw[j, 0])
            i, j = i[ok], j[ok]
            tested[i] += 1
            r = np.linalg.norm(Xw[i] - past.Xw[j], axis=1)
            votes[i[r > c.abs_m + c.rel * depth[i]]] += 1
        return votes, tested

    def check(self, T_world_cam: np.ndarray, uv: np.ndarray, depth: np.ndarray, desc: np.ndarray) -> np.ndarray:
        """uv: (N,2) ideal pixels; depth: (N,) metres (NaN: none); desc: (N,D). -> (N,) bool flagged as moving
        (seeds with ``min_votes`` and their region). The frame joins the history afterwards; ``seeds`` and
        ``tested`` (compared against ``min_votes`` past frames) stay readable until the next check."""
        c = self.cfg
        z = np.where((depth >= c.min_depth) & (depth <= c.max_depth), depth, np.nan)
        pts = self.cam.backproject(uv, np.nan_to_num(z)) if len(uv) else np.zeros((0, 3))
        Xw = pts @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        Xw[~np.isfinite(z)] = np.nan
        votes, tested = self.residual_votes(Xw, z, desc)
        seeds = votes >= c.min_votes
        self.seeds, self.tested = seeds, tested >= c.min_votes
        flagged = seeds | self._near(uv, z, uv[seeds], z[seeds])
        self.history.append(_Past(Xw, desc))
        self._region_uv, self._region_z = uv[flagged], z[flagged]
        return flagged

    def in_region(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(N,) bool: keypoints near the keypoints flagged in the last checked frame (a mover moves a few pixels
        per frame, so its region still covers it)."""
        return self._near(uv, depth, self._region_uv, self._region_z)

    def _near(self, uv: np.ndarray, z: np.ndarray, seed_uv: np.ndarray, seed_z: np.ndarray) -> np.ndarray:
        """Within ``region_px`` of a seed and, where both have depth, within ``region_depth_m`` of its depth."""
        out = np.zeros(len(uv), bool)
        if len(seed_uv) == 0 or len(uv) == 0:
            return out
        nb = cKDTree(seed_uv).query_ball_point(uv, self.cfg.region_px)
        counts = np.fromiter((len(n) for n in nb), np.int64, len(uv))
        i = np.repeat(np.arange(len(uv)), counts)  # all (keypoint, seed) pairs at once: ~8x the per-keypoint loop
        j = np.fromiter((k for n in nb for k in n), np.int64, int(counts.sum()))
        dz = np.abs(seed_z[j] - z[i])
        out[i[~np.isfinite(dz) | (dz <= self.cfg.region_depth_m)]] = True
        return out
