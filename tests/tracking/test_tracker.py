"""Tracker's recovery ladder on a hand-built map: which step gives the pose when the motion model is far off."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.features.depth import stereo_ur
from vslam.geometry.se3 import inv_T
from vslam.mapping.map import Map
from vslam.geometry.camera import project
from vslam.tracking.tracker import Tracker, TrackingConfig

CAM = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
BACKEND = BackendConfig()
STEREO = StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, BACKEND.rgbd_virtual_baseline, BACKEND.rgbd_disparity_sigma)


def _features(uv: np.ndarray, desc: np.ndarray) -> Features:
    return Features(uv.copy(), uv.copy(), desc, np.zeros(len(uv), np.int64), np.ones(len(uv)))


def _scene(rng: np.random.Generator) -> tuple[Map, np.ndarray, np.ndarray]:
    """One RGB-D keyframe at the origin seeing 300 points 1 m away and 80 points 8 m away. -> (map, the points'
    world positions (P,3), their descriptors (P,32))."""
    n_near, n_far = 300, 80
    uv = np.concatenate([rng.uniform([120, 40], [600, 440], (n_near, 2)), rng.uniform([40, 40], [600, 440], (n_far, 2))])
    z = np.concatenate([rng.uniform(0.9, 1.1, n_near), rng.uniform(7.5, 8.5, n_far)])
    xyz = np.column_stack([(uv[:, 0] - CAM.cx) / CAM.fx * z, (uv[:, 1] - CAM.cy) / CAM.fy * z, z])
    desc = rng.integers(0, 256, (len(z), 32), dtype=np.uint8)
    m = Map()
    kf = m.add_keyframe(0, 0.0, np.eye(4), _features(uv, desc), z, stereo_ur(uv, z, CAM.fx, STEREO.baseline))
    m.add_points(xyz, kf.id, np.arange(len(z)))
    return m, xyz, desc


def _frame(T_world_cam: np.ndarray, xyz: np.ndarray, desc: np.ndarray, rng: np.random.Generator) -> tuple[Features, np.ndarray]:
    """The scene's keypoints seen from ``T_world_cam`` (0.3 px noise) with their depth as virtual right x."""
    uv, z, vis = project(T_world_cam, xyz, CAM)
    uv = uv[vis] + rng.normal(0.0, 0.3, (int(vis.sum()), 2))
    return _features(uv, desc[vis]), stereo_ur(uv, z[vis], CAM.fx, STEREO.baseline)


def _pose_error_m(T: np.ndarray, T_true: np.ndarray) -> float:
    return float(np.linalg.norm((inv_T(T_true) @ T)[:3, 3]))


def test_a_far_off_prediction_hands_the_pose_to_the_reference_keyframe(monkeypatch):
    """The camera moved 12 cm sideways, the prediction says it stood still: the near points' true matches lie
    ~60 px from where the prediction projects them, outside the 15 px search, and only the far points are matched.
    Their PnP pose moves the local map farther than the search radius, so the reference keyframe's descriptor
    matching (independent of the prediction) gives the pose; with a good prediction it is never asked."""
    rng = np.random.default_rng(0)
    m, xyz, desc = _scene(rng)
    T_true = np.eye(4)
    T_true[0, 3] = 0.12
    feats, ur = _frame(T_true, xyz, desc, rng)
    asked: list[str] = []
    real = Tracker.track_keyframe
    monkeypatch.setattr(Tracker, "track_keyframe", lambda self, *a, **k: asked.append("reference") or real(self, *a, **k))

    res = Tracker(m, CAM, STEREO, TrackingConfig(), BACKEND).track(feats, ur, np.eye(4), 0, after_loss=False)
    assert res.ok and res.method == "reference" and asked == ["reference"]
    assert res.n_inliers > 200  # near and far points both
    assert _pose_error_m(res.T_world_cam, T_true) < 0.005

    asked.clear()  # off: the projection step's pose from the far points stands
    off = Tracker(m, CAM, STEREO, replace(TrackingConfig(), far_prediction_reference=False), BACKEND)
    res = off.track(feats, ur, np.eye(4), 0, after_loss=False)
    assert res.ok and res.method == "projection" and asked == []

    asked.clear()  # a prediction within reach: the projection step alone
    T_pred = T_true.copy()
    T_pred[0, 3] -= 0.01
    res = Tracker(m, CAM, STEREO, TrackingConfig(), BACKEND).track(feats, ur, T_pred, 0, after_loss=False)
    assert res.ok and res.method == "projection" and asked == []
    assert _pose_error_m(res.T_world_cam, T_true) < 0.005
