"""A small SLAM map of the synthetic room (320x240, RGB-D), built once per test process."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.features.depth import stereo_ur
from vslam.tracking.slam import SlamConfig, SlamTracker

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)


def seq(n: int = 40, **kw) -> SyntheticSequence:
    return SyntheticSequence(SyntheticConfig(n_frames=n, **{**SMALL, **kw}), sensor="rgbd")


@lru_cache(maxsize=1)
def room_map() -> tuple[SlamTracker, list, np.ndarray]:
    """(tracker after 40 frames, the frames, (40,4,4) tracked poses)."""
    s = seq()
    frames = list(s)
    st = SlamTracker(s.calibration, "rgbd", SlamConfig())
    poses = np.array([st.track(f).T_world_cam for f in frames])
    return st, frames, poses


def query(st: SlamTracker, frame):
    """Keypoints, depth-derived virtual right x of a frame, as the tracker computes them."""
    feats, right = st.front_end.extract(frame)
    depth = st.front_end.depth(frame, feats, right)
    return feats, stereo_ur(feats.uv, depth, st.cam.fx, st.baseline)
