"""Dynamic-object stage: keypoints and segments on moving things reach neither tracking nor mapping
(``DynamicFilter``: detector boxes / masks before tracking, the geometric motion check after)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vslam.dynamic import DynamicFilter
from vslam.tracking.stages.base import Stage


class DynamicStage(Stage):
    name = "dynamic"

    def __init__(self, dynamic: DynamicFilter):
        self.dynamic = dynamic
        self.ms = 0.0

    def filter(self, frame, front, feats, lines):
        t = time.perf_counter()
        kept = np.flatnonzero(self.dynamic.keep(frame, feats, front.objects))
        feats = feats.subset(kept)
        if lines is not None and len(lines):
            lines = lines.subset(np.flatnonzero(self.dynamic.keep_segments(frame, lines.raw, lines.segs)))
        self.ms = (time.perf_counter() - t) * 1e3
        return feats, lines, kept

    def drop(self, slam: Any, ok: bool, res, feats, depth, ur):
        """The geometric check on the frame's pose: keypoints found moving leave the frame before mapping, and
        the map points they matched are deleted so later frames cannot track against them."""
        moving = self.dynamic.observe(slam.T_world_cam, ok)
        if res is None:
            return feats, depth, ur
        slam.view.moving = moving
        if not moving.any():
            return feats, depth, ur
        for pid in res.point_ids[moving & (res.point_ids >= 0)]:
            slam.map.remove_point(int(pid))
        keep = np.flatnonzero(~moving)
        res.point_ids = res.point_ids[keep]
        return feats.subset(keep), depth[keep], ur[keep]

    def report(self, est, front) -> None:
        est.times_ms["dynamic"] = self.ms
        if front.objects is not None:
            est.times_ms["detector"] = front.ms["detector"]
