"""Geometric loop verification: the right keyframe is accepted with the right pose, a wrong place is rejected."""

from __future__ import annotations

import numpy as np

from vslam.geometry.se3 import inv_T
from vslam.loop.config import LoopConfig
from vslam.loop.verify import LoopVerifier
from tests.loop._map import query, room_map, seq


def _nearest_kf(st, frame_index: int) -> int:
    return min(st.map.keyframes.values(), key=lambda k: abs(k.frame_index - frame_index)).id


def _verifier(st):
    return LoopVerifier(st.cam, st.stereo_cam, LoopConfig(), st.cfg.backend)


def test_true_candidate_is_verified_with_the_tracked_pose():
    st, frames, poses = room_map()
    feats, ur = query(st, frames[25])
    match = _verifier(st).verify(st.map, feats, ur, _nearest_kf(st, 25))
    assert match is not None and match.n_inliers >= 100  # measured ~300
    D = inv_T(poses[25]) @ match.T_world_cam
    assert np.linalg.norm(D[:3, 3]) < 0.01  # same pose as tracking found, metres
    assert match.std_m < LoopConfig().max_std_m
    assert (match.point_ids >= 0).sum() == match.n_inliers


def test_wrong_place_is_rejected():
    st, frames, _ = room_map()
    street = seq(10, scene="street", seed=3)
    v = _verifier(st)
    for f in list(street)[::3]:  # another scene entirely
        feats, ur = query(st, f)
        for kf in st.map.keyframes:
            assert v.verify(st.map, feats, ur, kf) is None


def test_candidate_that_does_not_see_the_query_is_rejected():
    """The same room from the other side: similar texture statistics, no shared structure."""
    st, frames, _ = room_map()
    far = list(seq(90, seed=0))[80]  # 80 frames on, the camera faces another wall (seed 0 path, 0.6 laps)
    feats, ur = query(st, far)
    v = _verifier(st)
    assert all(v.verify(st.map, feats, ur, kf) is None for kf in list(st.map.keyframes)[:2])
