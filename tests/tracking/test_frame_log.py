"""FrameLog: frames follow their reference keyframe through later global changes of the map."""

from __future__ import annotations

import numpy as np

from vslam.features.base import Features
from vslam.geometry.se3 import make_T, so3_exp
from vslam.mapping.map import Map
from vslam.tracking.frame_log import FrameLog
from vslam.tracking.vio import transform_map


def _map_with_keyframe(T: np.ndarray) -> Map:
    m = Map()
    m.add_keyframe(0, 0.0, T, Features.empty(), np.zeros(0), np.zeros(0))
    return m


def test_frames_follow_a_moved_keyframe_and_a_rescaled_map() -> None:
    T_kf = make_T(so3_exp(np.array([0.1, -0.2, 0.3])), np.array([1.0, 2.0, 3.0]))
    m = _map_with_keyframe(T_kf)
    log = FrameLog(m)
    T_frame = T_kf @ make_T(so3_exp(np.array([0.0, 0.05, 0.0])), np.array([0.2, 0.0, 0.1]))
    log.record(5, 0, T_frame)
    log.record(6, None, np.eye(4))  # before any keyframe: an absolute pose
    np.testing.assert_allclose(log.poses([5, 6]), [T_frame, np.eye(4)], atol=1e-12)
    assert not log.moved

    # A monocular map rescaled to metres (x' = T (s x)), as the inertial initialisation does.
    s, T = 2.5, make_T(so3_exp(np.array([0.0, 0.0, 0.4])), np.array([0.5, 0.0, 0.0]))
    transform_map(m, T, s)
    log.transform(T, s)
    assert log.moved
    expect = T_frame.copy()
    expect[:3, 3] *= s
    np.testing.assert_allclose(log.poses([5])[0], T @ expect, atol=1e-12)
    np.testing.assert_allclose(log.poses([6])[0], T, atol=1e-12)

    # A loop correction moves the keyframe alone: the frame keeps its pose relative to it.
    rel = np.linalg.inv(m.keyframes[0].T_world_cam) @ log.poses([5])[0]
    m.keyframes[0].T_world_cam = make_T(np.eye(3), np.array([9.0, 0.0, 0.0])) @ m.keyframes[0].T_world_cam
    np.testing.assert_allclose(np.linalg.inv(m.keyframes[0].T_world_cam) @ log.poses([5])[0], rel, atol=1e-12)


def test_identity_transform_is_not_a_move() -> None:
    log = FrameLog(_map_with_keyframe(np.eye(4)))
    log.record(0, 0, np.eye(4))
    log.transform(np.eye(4), 1.0)
    assert not log.moved
