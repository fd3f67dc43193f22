"""Visual-inertial SLAM (``slam.inertial``) end to end on short synthetic sequences.

320x240 static room, RGB-D, realistic IMU noise and bias random walk (SyntheticConfig defaults). The rig moves
from frame 0, so the IMU is initialised by visual-inertial alignment. One sequence with a 1 s camera blackout
serves both comparisons; frames are rendered once and fed to both trackers.
"""

from __future__ import annotations

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import Trajectory
from vslam.eval import EvalConfig, evaluate
from vslam.tracking.slam import SlamConfig, SlamTracker
from vslam.tracking.vio import VioConfig

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)
BLACK = (60, 30)  # frames 60..89 all black: 1 s at 30 frames/s


def _run(seq, frames, cfg):
    st = SlamTracker(seq.calibration, seq.sensor, cfg)
    stamps, poses, tracked = [], [], []
    for f in frames:
        e = st.track(f)
        stamps.append(f.timestamp), poses.append(e.T_world_cam), tracked.append(e.tracked)
    traj = Trajectory(np.array(stamps), np.array(poses))
    return st, traj, _ate(traj, seq), np.array(tracked)


def _ate(traj, seq):
    return evaluate(traj, seq.groundtruth(), EvalConfig(align="se3", plots=False))


@pytest.fixture(scope="module")
def blackout_runs():
    seq = SyntheticSequence(SyntheticConfig(n_frames=110, blackouts=(BLACK,), **SMALL), sensor="rgbd")
    frames = list(seq)
    vision = _run(seq, frames, SlamConfig())
    vio = _run(seq, frames, SlamConfig(inertial=VioConfig(enabled=True)))
    return seq, vision, vio


def test_vio_stays_close_to_vision_only_before_the_blackout(blackout_runs):
    """On the 2 s before the blackout (own SE3 alignment), where both see the same frames. Measured: vision-only
    0.0039 m, VIO 0.0052 m. The IMU no longer adds accuracy here: vision-only went 0.0168 -> 0.0056 -> 0.0039 m
    with the RGB-D disparity model and ORB-SLAM's culling rule, VIO 0.0117 -> 0.0050 -> 0.0052 m (issue 8 keeps
    this open). Where vision fails, the blackout test below, VIO clearly wins."""
    seq, (_, traj_v, _, _), (st, traj_i, _, _) = blackout_runs
    assert st.vio is not None and st.vio.ready and st.vio.method == "dynamic"
    before = np.arange(BLACK[0])
    ate_v = _ate(traj_v.subset(before), seq).ate.translation.rmse
    ate_i = _ate(traj_i.subset(before), seq).ate.translation.rmse
    # measured here VIO 0.0053 m vs vision-only 0.0039 m (1.38x; scene seeds 1000 / 2000: 0.90x / 0.90x; the same to
    # 1e-15 with 1 CPU and single-threaded BLAS). Catches an IMU that pulls the visual estimate off (wrong extrinsics,
    # gravity or noise weights): bounds 2x vision-only and 1.5x the measured VIO value
    assert ate_i < 2.0 * ate_v, (ate_i, ate_v)
    assert ate_i < 0.008, ate_i


def test_blackout_is_bridged_by_the_imu(blackout_runs):
    _, (_, _, res_v, tr_v), (_, _, res_i, tr_i) = blackout_runs
    b0, b1 = BLACK[0], BLACK[0] + BLACK[1]
    assert not tr_i[b0:b1].any() and not tr_v[b0:b1].any()  # black frames are predicted, never "tracked"
    assert tr_i[b1:].all()  # tracking recovers right after, around the IMU-predicted pose
    err_v, err_i = res_v.arrays.ate_t[b0:b1].max(), res_i.arrays.ate_t[b0:b1].max()
    # measured: the constant-velocity prediction drifts 0.26 m by the end of the blackout, the IMU's 0.037 m (7x; scene
    # seeds 1000 / 2000: vision-only 0.40 / 0.12 m, so an absolute bound on it, 0.2 m, tested the scene). Catches an
    # IMU prediction that does not bridge the gap: it must beat the constant-velocity one 3x and stay under 0.06 m
    assert err_v > 3 * err_i, (err_v, err_i)
    assert err_i < 0.06, err_i
    assert res_i.ate.translation.rmse < 0.035  # measured 0.0236 m over all 110 frames (vision-only 0.229 m)


def test_inertial_off_changes_nothing():
    seq = SyntheticSequence(SyntheticConfig(n_frames=12, **SMALL), sensor="rgbd")
    frames = list(seq)
    _, a, _, _ = _run(seq, frames, SlamConfig())
    _, b, _, _ = _run(seq, frames, SlamConfig(inertial=VioConfig(enabled=False)))
    np.testing.assert_array_equal(a.poses, b.poses)


def test_inertial_without_imu_is_a_one_line_config_error():
    """A sequence with no IMU (TUM, KITTI) and slam.inertial on: a ConfigError naming the switch, not a traceback
    from the first keyframe's static initialisation."""
    import dataclasses

    from vslam.errors import ConfigError

    seq = SyntheticSequence(SyntheticConfig(n_frames=2, width=160, height=120, fx=131.25, fy=131.25), "rgbd")
    calib = dataclasses.replace(seq.calibration, imu=None)
    with pytest.raises(ConfigError, match="slam.inertial.enabled"):
        SlamTracker(calib, "rgbd", SlamConfig(inertial=VioConfig(enabled=True)))
