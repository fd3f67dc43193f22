"""Visual-inertial stage: IMU samples per frame, IMU prediction, keyframe requests, initialisation (``Vio``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vslam.tracking.stages.base import Stage
from vslam.tracking.vio import Vio


class InertialStage(Stage):
    name = "inertial"

    def __init__(self, vio: Vio):
        self.vio = vio

    def on_frame(self, frame) -> None:
        self.vio.add_imu(frame)

    def annotate(self, est) -> None:
        est.imu = self.vio.imu_state

    def predict(self, frame, T_pred: np.ndarray) -> np.ndarray:
        T_imu = self.vio.predict(frame.timestamp)
        return T_pred if T_imu is None else T_imu  # once initialised, IMU propagation replaces constant velocity

    def on_pose(self, slam: Any, frame, ok: bool) -> None:
        self.vio.update(frame.timestamp, slam.T_world_cam, ok)

    def wants_keyframe(self, frame, res, status: str) -> bool:
        return res.ok and status != "no_depth" and self.vio.wants_keyframe(frame.timestamp)

    def on_keyframe(self, slam: Any, kf, frame, res) -> None:
        if res is not None:  # a map's first keyframe has no inertial state to take yet
            self.vio.new_keyframe(kf.id)

    def after_mapping(self, slam: Any, kf) -> None:
        self.vio.after_keyframe(kf.id)

    def end_frame(self, slam: Any) -> None:
        """Static / dynamic IMU initialisation and its refinements (``Vio.try_initialize``). Monocular, the map was
        just scaled to metres, so the tracker's own pose state follows; after a dynamic alignment one VI BA links
        every keyframe (ORB-SLAM3's inertial BA after its initialisation)."""
        vio = self.vio
        out = vio.try_initialize()
        if out is None:
            return
        T, scale = out
        slam.T_world_cam = vio.transform_pose(slam.T_world_cam, T, scale)
        slam.frames.transform(T, scale)  # monocular: the frames tracked so far were at the old map scale
        for s in slam.stages:
            s.on_transform(T, scale)
        slam.scale_motion(scale)
        if vio.method == "dynamic" and slam.ref_kf is not None:  # (and refinements)
            last = max(slam.map.keyframes)
            vio.full_chain = True  # one VI BA over every keyframe
            slam.mapper.bundle_adjust(last)
            vio.full_chain = False
            vio.after_keyframe(last)
            if slam.last_kf_frame == slam.n_frames:  # this frame is that keyframe: follow the BA
                slam.T_world_cam = slam.map.keyframes[last].T_world_cam.copy()

    def on_map(self, slam: Any, m) -> None:
        self.vio.map = m

    def on_new_map(self) -> None:
        self.vio.new_map()

    def finish(self, slam: Any, out: Path) -> dict[str, Path]:
        self.vio.finish()
        return {}
