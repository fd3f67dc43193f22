"""Line stage: LSD segments per frame, Plücker map lines, the tracked pose refined on points and lines
(``LineSlam``)."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from vslam.features.lines import LineFeatures
from vslam.mapping.line_map import LineSlam
from vslam.tracking.stages.base import Stage


class LineStage(Stage):
    """``beside``: LSD runs on a thread of its own, beside the keypoint network (``RuntimeConfig.lines_beside_networks``)."""

    name = "lines"

    def __init__(self, slam: Any, beside: bool):
        self._make = lambda m: LineSlam(m, slam.cam, slam.stereo_cam, slam.sensor, slam.cfg.lines, slam.cfg.backend,
                                        slam.calib)
        self.lines = self._make(slam.map)
        slam.mapper.lines = self.lines
        self.stereo = slam.sensor == "stereo"
        self.rgbd = slam.sensor == "rgbd"
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="lines") if beside else None
        self.feats: LineFeatures | None = None  # this frame's segments (after dynamic filtering)
        self.ids = None  # the map line matched per segment once the pose is refined
        self.pre_init: dict[int, LineFeatures] = {}  # monocular: segments of frames before the map exists

    # -- front end (image only) ------------------------------------------------
    def depth(self, frame):
        """The depth map a keyframe's new lines are measured with (RGB-D); stereo lines come from the end-point
        depths the rig measured (``LineSlam.from_rig``) and from two keyframes, mono lines from two keyframes in
        local mapping (``LineSlam.triangulate``)."""
        return frame.depth if self.rgbd else None

    def detect(self, frame) -> LineFeatures:
        return self.lines.detect(frame.image, self.depth(frame), frame.right if self.stereo else None)

    def submit(self, frame) -> Future | None:
        return self.pool.submit(self.detect, frame) if self.pool is not None else None

    # -- per frame -------------------------------------------------------------
    def on_features(self, slam: Any, frame, feats, lines) -> None:
        self.feats, self.ids = lines, None
        if slam.mono_init is not None and slam.ref_kf is None:  # the initialiser's reference may be any recent frame
            self.pre_init[frame.index] = lines
            self.pre_init = dict(list(self.pre_init.items())[-(slam.mono_init.max_tries + 2):])

    def measure(self, slam: Any, frame, feats, ur, T_pred, res):
        if res.ok:  # the pose on points + matched map lines
            res.T_world_cam, self.ids = self.lines.refine_tracked(
                res.T_world_cam, res.point_ids, feats, ur, self.feats, slam.ref_kf, slam.cfg.tracking.local_keyframes)
        return res

    def on_keyframe(self, slam: Any, kf, frame, res) -> None:
        self.lines.add_keyframe(kf.id, kf.T_world_cam, self.feats, self.ids, self.depth(frame))

    def on_two_view_map(self, slam: Any, kfs, frame) -> None:
        for k in kfs:  # the two views' segments, so the first keyframes can triangulate lines
            lf = self.feats if k is kfs[1] else self.pre_init.get(k.frame_index)
            if lf is not None:
                self.lines.add_keyframe(k.id, k.T_world_cam, lf, None, None)
        self.pre_init = {}

    def on_transform(self, T, scale: float) -> None:
        self.lines.transform(T, scale)

    def report(self, est, front) -> None:
        est.times_ms["lines"] = front.ms["lines"]
        est.n_lines = len(self.feats)
        est.n_line_inliers = int((self.ids >= 0).sum()) if self.ids is not None else 0

    def on_map(self, slam: Any, m) -> None:
        self.lines = self._make(m)  # lines live in one map: the new map grows its own
        slam.mapper.lines = self.lines

    def stats(self) -> dict[str, int]:
        return self.lines.stats()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()

    def finish(self, slam: Any, out: Path) -> dict[str, Path]:
        return {"lines": self.lines.write_ply(out / "map_lines.ply")}
