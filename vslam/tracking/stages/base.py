"""The interface of an optional SLAM stage: hooks ``SlamTracker`` calls at fixed points of every frame.

A stage (loop closing, visual-inertial, lines, dynamic filtering, dense depth tracking) is built from its config when enabled
and appended to ``SlamTracker.stages``; the tracker calls each hook on every stage in list order, and a hook a
stage does not override does nothing. So adding a stage means writing one module and one line in
``build_stages``, not editing ``track``. The hooks, in the order a frame meets them:

- ``on_frame(frame)``: before anything (the IMU takes the frame's samples).
- ``filter(frame, front, feats, lines)``: which keypoints / segments tracking may use (dynamic objects).
- ``on_features(slam, frame, feats, lines)``: what the frame kept (lines: this frame's segments).
- ``annotate(est)``: fields of the frame's ``FrameEstimate`` known before tracking.
- ``predict(frame, T_pred)``: the pose prior (IMU propagation replaces constant velocity).
- ``measure(slam, frame, feats, ur, T_pred, res)``: a step of the recovery ladder, given the result so far
  (place relocalisation of a lost frame; lines refine a tracked pose; dense depth tracking tries a frame
  features lost).
- ``on_pose(slam, frame, res)``: the frame's pose is decided (tracked or predicted).
- ``drop(slam, ok, res, feats, depth, ur)``: keypoints to leave out of mapping once the pose is known (``res``
  None on a map's first frame).
- ``on_two_view_map(slam, kfs, frame)``: a monocular map was just made from two views.
- ``wants_keyframe(frame, res, status)`` / ``decides_keyframe(method, depth, min_inliers)``: keyframe requests.
- ``on_keyframe(slam, kf, frame, res)``: a keyframe was made, before local mapping (``res`` None for the first
  keyframe of a map); ``after_mapping(slam, kf)``: local mapping has run (its BA perhaps still in the worker);
  ``after_local_ba(slam, kf, image)``: the keyframe's local BA is written back (the loop step) -> ms per step.
- ``end_frame(slam)``: the frame is done (IMU initialisation); ``on_transform(T, scale)``: the map was moved by
  a similarity (the IMU initialisation's gravity alignment and metric scale).
- ``report(est, front)``: stage timings and counts into the ``FrameEstimate``.
- ``on_map(slam, m)``: the map every stage works on changed (a new map, a merge, a loaded map);
  ``on_new_map()``: a new map was started.
- ``moved_map()``: whether keyframes moved after their frames' poses were written (a loop correction).
- ``finish(slam, out)``: end of the run; files written.

``slam`` is the ``SlamTracker``: a stage reads its pose state and writes the pose where its step decides it
(e.g. the IMU initialisation rescales the monocular map and the tracker's pose with it).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from vslam.data.types import Frame
    from vslam.features import Features
    from vslam.features.lines import LineFeatures
    from vslam.mapping.map import Keyframe, Map
    from vslam.tracking.baseline import FrameEstimate
    from vslam.tracking.tracker import TrackResult


class Stage:
    """An optional part of SLAM (see the module docstring for the hooks); every hook defaults to nothing."""

    name = ""

    def on_frame(self, frame: Frame) -> None:
        pass

    def filter(self, frame: Frame, front: Any, feats: Features,
               lines: LineFeatures | None) -> tuple[Features, LineFeatures | None, np.ndarray | None]:
        """-> the keypoints and segments kept, and the kept keypoints' indices into ``feats`` (None: all)."""
        return feats, lines, None

    def on_features(self, slam: Any, frame: Frame, feats: Features, lines: LineFeatures | None) -> None:
        pass

    def annotate(self, est: FrameEstimate) -> None:
        pass

    def predict(self, frame: Frame, T_pred: np.ndarray) -> np.ndarray:
        return T_pred

    def measure(self, slam: Any, frame: Frame, feats: Features, ur: np.ndarray, T_pred: np.ndarray,
                res: TrackResult) -> TrackResult:
        return res

    def on_pose(self, slam: Any, frame: Frame, ok: bool) -> None:
        pass

    def drop(self, slam: Any, ok: bool, res: TrackResult | None, feats: Features, depth: np.ndarray,
             ur: np.ndarray) -> tuple[Features, np.ndarray, np.ndarray]:
        return feats, depth, ur

    def on_two_view_map(self, slam: Any, kfs: list[Keyframe], frame: Frame) -> None:
        pass

    def wants_keyframe(self, frame: Frame, res: TrackResult, status: str) -> bool:
        return False

    def decides_keyframe(self, method: str, depth: np.ndarray, min_inliers: int) -> bool | None:
        """True / False where this stage measured the frame (``TrackResult.method``) and its own rule decides;
        None: the tracker's rule."""
        return None

    def on_keyframe(self, slam: Any, kf: Keyframe, frame: Frame, res: TrackResult | None) -> None:
        pass

    def after_mapping(self, slam: Any, kf: Keyframe) -> None:
        pass

    def after_local_ba(self, slam: Any, kf: Keyframe, image: np.ndarray | None) -> dict[str, float]:
        """A keyframe whose local BA is written back (at once, or when the BA worker's result lands) -> ms per
        step."""
        return {}

    def end_frame(self, slam: Any) -> None:
        pass

    def on_transform(self, T: np.ndarray, scale: float) -> None:
        pass

    def report(self, est: FrameEstimate, front: Any) -> None:
        pass

    def on_map(self, slam: Any, m: Map) -> None:
        pass

    def on_new_map(self) -> None:
        pass

    def moved_map(self) -> bool:
        """Whether this stage moved keyframes after their frames' poses were written (a loop correction)."""
        return False

    def stats(self) -> dict[str, int]:
        return {}

    def finish(self, slam: Any, out: Path) -> dict[str, Path]:
        return {}
