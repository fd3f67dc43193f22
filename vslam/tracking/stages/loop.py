"""Loop closing and place relocalisation (``vslam.loop.closing.LoopCloser``) as a stage: a lost frame is looked
for among all keyframes of the map by place recognition, and every keyframe, once its local BA is written back,
is added to the place database and checked for a loop (SE3, or Sim3 for monocular maps)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from vslam.loop.closing import LoopCloser
from vslam.tracking.stages.base import Stage


class LoopStage(Stage):
    name = "loop"

    def __init__(self, loop: LoopCloser, relocalise: bool):
        self.loop, self.relocalise = loop, relocalise

    def measure(self, slam: Any, frame, feats, ur, T_pred, res):
        if res.ok or not self.relocalise:
            return res
        return self.loop.relocalise(slam.tracker, feats, ur, frame.image) or res

    def on_two_view_map(self, slam: Any, kfs, frame) -> None:
        for k in kfs:  # the reference view's image is gone: an image descriptor sees only the second
            self.loop.add_keyframe(k, frame.image if k is kfs[1] else None)

    def after_local_ba(self, slam: Any, kf, image) -> dict[str, float]:
        t = time.perf_counter()
        self.loop.add_keyframe(kf, image)
        if self.loop.last_scale != 1.0:  # a monocular loop rescaled this part of the map
            slam.rescale_motion(self.loop.last_scale)
            self.loop.last_scale = 1.0
        return {"loop": (time.perf_counter() - t) * 1e3}

    def on_map(self, slam: Any, m) -> None:
        self.loop.map = m

    def moved_map(self) -> bool:
        return self.loop.stats.corrected > 0

    def finish(self, slam: Any, out: Path) -> dict[str, Path]:
        return {"loops": self.loop.write_stats(out / "loops.json")}
