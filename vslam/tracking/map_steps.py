"""``SlamTracker``'s steps around its map: the map's start (depth, or the monocular two-view initialisation and
the frames seen before it), a tracked frame's status and the keyframe decision, the BA worker's write-back and
the stages' steps after a keyframe's local BA (the loop step).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from vslam.data.types import Frame
from vslam.features import Features
from vslam.geometry.se3 import inv_T
from vslam.tracking.tracker import need_keyframe

log = logging.getLogger(__name__)


class MapSteps:
    """The keyframe-side steps of ``SlamTracker`` (a base class: the methods read and set the tracker's map,
    pose and reference keyframe)."""

    def _initialize(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray,
                    T0: np.ndarray | None = None) -> bool:
        """Start the map (RGB-D / stereo: this frame's depth, its keyframe at ``T0``, the identity for the first
        map; monocular: the two-view initialiser)."""
        if self.cfg.load_map:  # a saved map: the first frame is placed in it by place recognition
            res = self.loop.relocalise(self.tracker, feats, ur, frame.image)  # type: ignore[union-attr]
            if res is None:
                return False
            self.T_world_cam, self.ref_kf = res.T_world_cam, self.tracker.best_reference(res.point_ids, -1)
            return self.ref_kf >= 0
        if self.mono_init is not None:
            kfs = self.mono_init.try_initialize(self.map, frame.index, frame.timestamp, feats, self.stereo_cam,
                                                self.cfg.backend, self.cfg.init_ba)
            if kfs is None:
                return False
            self.ref_kf, self.last_kf_frame = kfs[1].id, self.n_frames
            self.T_world_cam = kfs[1].T_world_cam.copy()
            for s in self.stages:
                s.on_two_view_map(self, kfs, frame)
            return True
        if int(np.isfinite(depth).sum()) < self.cfg.tracking.min_depth_points:
            return False
        T0 = np.eye(4) if T0 is None else T0
        kf = self.map.add_keyframe(frame.index, frame.timestamp, T0, feats, depth, ur)
        for s in self.stages:
            s.on_keyframe(self, kf, frame, None)
        self.mapper.process(kf, np.full(len(feats), -1, np.int64))
        self._after_local_ba(kf, frame.image)
        self.ref_kf, self.last_kf_frame = kf.id, self.n_frames
        self.T_world_cam = T0.copy()
        return True

    def _backfill(self) -> dict[int, np.ndarray]:
        """Monocular, right after the two-view initialisation: poses of the frames seen before it, by descriptor
        matching + PnP + pose-only refinement against the initial map (``Tracker.track_keyframe`` on the first
        keyframe; frames between the two views see its points). -> {frame index: T_world_cam}; frames that do
        not localise are left out."""
        from scipy.spatial import cKDTree

        kf0 = self.map.keyframes[min(self.map.keyframes)]  # the reference view defines the world
        out = {kf0.frame_index: kf0.T_world_cam.copy()}
        for idx, feats in self._pre_init:
            if idx in out or len(feats) < self.cfg.tracking.min_inliers:
                continue
            res = self.tracker.track_keyframe(feats, np.full(len(feats), np.nan), kf0.id, cKDTree(feats.uv), "backfill")
            if res is not None and res.ok:
                out[idx] = res.T_world_cam
        self._pre_init = []
        for idx, T in out.items():  # they follow kf0 when the map moves later (loop, mono-inertial scale)
            self.frames.record(idx, kf0.id, T)
        return out

    def _status(self, ok: bool, method: str, depth: np.ndarray) -> str:
        """FrameEstimate.status of a frame after initialisation (see there)."""
        if not ok:
            return "predicted"
        if method in ("relocalised", "dense"):  # dense: the depth ICP of vslam.tracking.dense
            return method
        if self.sensor != "mono" and int(np.isfinite(depth).sum()) < self.cfg.tracking.min_depth_points:
            return "no_depth"  # measured from 2-D matches only: weaker, and the frame cannot become a keyframe
        return "tracked"

    def _want_keyframe(self, frame: Frame, n_inliers: int, point_ids: np.ndarray, depth: np.ndarray, method: str = "") -> bool:
        tc = self.cfg.tracking
        if self.sensor != "mono" and int(np.isfinite(depth).sum()) < tc.min_depth_points:
            return False  # a keyframe without depth would add no points
        for s in self.stages:  # a stage that measured the frame (depth ICP) has its own rule
            d = s.decides_keyframe(method, depth, tc.kf_min_inliers)
            if d is not None:
                return d
        ref = self.map.keyframes[self.ref_kf]  # type: ignore[index]
        min_obs = min(3, len(self.map.keyframes))  # ORB-SLAM: 2 while the map has <= 2 keyframes; 1 for the first
        ref_ids = ref.point_ids[ref.point_ids >= 0]
        points = self.map.points
        ref_tracked = sum(1 for p in ref_ids.tolist() if len(points[p].observations) >= min_obs)
        close = np.isfinite(depth) & (depth < tc.close_baselines * self.baseline)
        n_close_tracked = int(np.sum(close & (point_ids >= 0)))
        n_close_untracked = int(np.sum(close & (point_ids < 0)))
        return need_keyframe(n_inliers, ref_tracked, self.n_frames - self.last_kf_frame, n_close_tracked,
                             n_close_untracked, self.sensor, tc)

    def _flush_mapping(self) -> dict[str, float]:
        """Write back the worker's local BA, then run the loop step that waited for it; the current pose follows
        the keyframe (as the keyframe's own pose does when BA runs at once). -> ms per step, "flush" the total."""
        t = time.perf_counter()
        kf, image, _ = self._pending  # type: ignore[misc]
        self._pending = None
        T_before = kf.T_world_cam.copy()
        ms = {"wait": self.mapper.flush()}
        self._rel_scale = 1.0
        ms.update(self._after_local_ba(kf, image))
        rel = inv_T(T_before) @ self.T_world_cam
        rel[:3, 3] *= self._rel_scale
        self.T_world_cam = kf.T_world_cam @ rel
        ms["flush"] = (time.perf_counter() - t) * 1e3
        return ms

    def _after_local_ba(self, kf, image: np.ndarray) -> dict[str, float]:
        """The stages' steps for a keyframe whose local BA is written back (place recognition and a loop
        correction) -> ms per step."""
        ms: dict[str, float] = {}
        for s in self.stages:
            ms.update(s.after_local_ba(self, kf, image))
        return ms

    def scale_motion(self, scale: float) -> None:
        """The map's unit changed by ``scale`` (the IMU's metric scale, a monocular merge or loop): the motion
        model's translation follows (a new array: the old one may be held elsewhere)."""
        self.velocity = self.velocity.copy()
        self.velocity[:3, 3] *= scale

    def rescale_motion(self, scale: float) -> None:
        """A monocular loop rescaled the map around the current keyframe: the motion model follows, and the frame
        tracked after a BA write-back keeps its offset at that scale (``_flush_mapping``)."""
        self.scale_motion(scale)
        self._rel_scale = scale
