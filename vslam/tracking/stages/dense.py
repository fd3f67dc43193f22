"""RGB-D dense stage: ICP of the depth against the last keyframe where features fail (``DenseOdometry``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from vslam.mapping.map import PoseLink
from vslam.tracking.dense import DenseOdometry
from vslam.tracking.stages.base import Stage


class DenseStage(Stage):
    name = "dense"

    def __init__(self, dense: DenseOdometry):
        self.dense = dense

    def measure(self, slam: Any, frame, feats, ur, T_pred, res):
        if res.ok:
            return res
        # too few features: ICP of the depth against the keyframe's
        return self.dense.track_frame(frame, T_pred, slam.map, len(feats)) or res

    def on_map(self, slam: Any, m) -> None:
        # another map (taken up again, or merged): a reference outside it has a pose in another frame
        if self.dense.ref_id is None or self.dense.ref_id not in m.keyframes:
            self.dense.clear_reference()

    def decides_keyframe(self, method: str, depth: np.ndarray, min_inliers: int) -> bool | None:
        if method != "dense":
            return None
        # its reference fell behind, or features are back
        return self.dense.wants_keyframe or int(np.isfinite(depth).sum()) >= min_inliers

    def on_keyframe(self, slam: Any, kf, frame, res) -> None:
        if res is not None and res.method == "dense" and self.dense.last_link is not None:
            ref, T_ref_cam, cov = self.dense.last_link  # BA keeps the ICP's motion
            slam.map.links.append(PoseLink(ref, kf.id, T_ref_cam, cov))
        self.dense.set_reference(kf.id, kf.T_world_cam, frame.depth, frame.image)
