"""Inertial initialisation inside the tracker (``vslam.tracking.vio.Vio``) without the visual front end.

Keyframes are placed at the ground-truth poses of a synthetic sequence (realistic IMU noise), scaled as a
monocular map would be (arbitrary scale) and slightly perturbed; the IMU arrives frame by frame as in a run.
The full mono-inertial SLAM number is the ``vio-room-mono`` benchmark row (a test run would take minutes).
"""

from __future__ import annotations

import numpy as np

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.types import Frame
from vslam.features.base import Features
from vslam.geometry.se3 import inv_T, make_T, so3_exp
from vslam.mapping.map import Map
from vslam.tracking.vio import Vio, VioConfig

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)


def _feed(seq, sensor, map_scale, n=60, every=5, seed=0, noise=1e-3, cfg=VioConfig(enabled=True)):
    rng = np.random.default_rng(seed)
    gt = seq.groundtruth().poses
    T0 = inv_T(gt[0])  # map frame = the first keyframe's camera
    m = Map()
    vio = Vio(seq.calibration, sensor, cfg, m)
    out = None
    for i in range(n):
        t = float(seq.timestamps()[i])
        vio.add_imu(Frame(i, t, np.zeros((1, 1), np.uint8), imu=seq.frame_imu(i)))
        if i % every == 0:
            T = T0 @ gt[i]
            if i > 0:  # visual noise: `noise` rad and m per axis
                T = T @ make_T(so3_exp(rng.normal(0, noise, 3)), rng.normal(0, noise, 3))
            T[:3, 3] *= map_scale
            m.add_keyframe(i, t, T, Features.empty(), np.zeros(0), np.zeros(0))
        out = vio.try_initialize()
        if out is not None:  # later keyframes would come from the tracker in metres; stop here
            break
    return vio, m, gt, T0, out


def test_mono_inertial_alignment_makes_the_map_metric():
    seq = SyntheticSequence(SyntheticConfig(n_frames=60, **SMALL), sensor="mono")
    vio, m, gt, T0, out = _feed(seq, "mono", map_scale=0.37)
    assert out is not None and vio.ready and vio.method == "dynamic"
    kfs = sorted(m.keyframes.values(), key=lambda k: k.timestamp)
    est = np.array([np.linalg.norm(k.T_world_cam[:3, 3]) for k in kfs[1:]])
    true = np.array([np.linalg.norm((T0 @ gt[k.frame_index])[:3, 3]) for k in kfs[1:]])
    scale = float(est @ true / (est @ est)) ** -1  # least squares est = scale * true
    assert abs(scale - 1.0) < 0.02  # measured 0.990 (1.002 without the 1 mm visual noise)
    g_true = T0[:3, :3] @ np.array([0.0, 0.0, -9.81])
    g = np.asarray(vio.params.n_gravity)
    assert np.degrees(np.arccos(g @ g_true / 9.81 / np.linalg.norm(g))) < 1.0  # measured 0.32 deg
    speed_err = [np.linalg.norm(k.velocity) - np.linalg.norm(seq.motion.body_state(np.array([k.timestamp - kfs[0].timestamp])).v[0])
                 for k in kfs]
    assert np.max(np.abs(speed_err)) < 0.03  # m/s, measured 0.011


def test_stereo_alignment_keeps_the_map_scale():
    seq = SyntheticSequence(SyntheticConfig(n_frames=60, **SMALL), sensor="stereo")
    vio, m, gt, T0, out = _feed(seq, "stereo", map_scale=1.0)
    assert out is not None and out[1] == 1.0 and vio.method == "dynamic"
    kf = m.keyframes[max(m.keyframes)]
    np.testing.assert_allclose(kf.T_world_cam[:3, 3], (T0 @ gt[kf.frame_index])[:3, 3], atol=0.005)  # measured 1.4 mm
