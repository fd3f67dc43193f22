"""Visual-inertial alignment on synthetic keyframes given up to an arbitrary similarity."""

from __future__ import annotations

import numpy as np
import pytest

from tests.inertial._synth import synthetic_imu
from vslam.errors import InertialError
from vslam.geometry.se3 import so3_exp
from vslam.inertial import make_bias, make_params, preintegrate
from vslam.inertial.init import vi_align

R_VIS = so3_exp(np.array([0.4, -0.9, 0.3]))  # visual frame: gravity anywhere
SCALE = 3.7  # metric = SCALE * visual


def _keyframes(noise: bool):
    cfg, motion, imu, truth = synthetic_imu(4.0, noise=noise)
    idx = np.arange(0, len(imu.t), 50)  # 4 keyframes per second
    times = imu.t[idx]
    T_wc = motion.T_world_cam0(times - cfg.start_time)
    T_vc = T_wc.copy()
    T_vc[:, :3, :3] = R_VIS @ T_wc[:, :3, :3]
    T_vc[:, :3, 3] = T_wc[:, :3, 3] @ R_VIS.T / SCALE + np.array([1.0, 2.0, 3.0])
    return cfg, motion, imu, truth, idx, times, T_vc


def _gravity_err_deg(al) -> float:
    up = al.R_world_visual @ R_VIS @ np.array([0.0, 0.0, 1.0])
    return float(np.degrees(np.arccos(np.clip(up[2], -1, 1))))


@pytest.mark.parametrize("noise, scale_tol, grav_tol, bg_tol, ba_tol",
                         [(False, 0.001, 0.01, 5e-5, 1e-3), (True, 0.01, 0.2, 3e-4, 0.03)])
def test_vi_align_recovers_scale_gravity_biases(noise, scale_tol, grav_tol, bg_tol, ba_tol) -> None:
    cfg, motion, imu, truth, idx, times, T_vc = _keyframes(noise)
    al = vi_align(times, T_vc, motion.T_body_cam0, imu=imu, params=make_params(cfg.imu_noise))  # biases start at 0
    assert abs(al.scale / SCALE - 1) < scale_tol, al.scale
    assert _gravity_err_deg(al) < grav_tol
    assert np.linalg.norm(al.gyro_bias - truth.gyro_bias[idx].mean(axis=0)) < bg_tol
    assert np.linalg.norm(al.accel_bias - truth.accel_bias[idx].mean(axis=0)) < ba_tol
    # Speeds are yaw-free, so compare them directly (m/s).
    assert np.max(np.abs(np.linalg.norm(al.velocities, axis=1) - np.linalg.norm(truth.v_world[idx], axis=1))) < 0.02
    # metric_poses: camera path length in metres and gravity along world -z.
    metric = al.metric_poses(T_vc)
    true_cam = motion.T_world_cam0(times - cfg.start_time)
    path = np.linalg.norm(np.diff(metric[:, :3, 3], axis=0), axis=1).sum()
    true_path = np.linalg.norm(np.diff(true_cam[:, :3, 3], axis=0), axis=1).sum()
    assert true_path > 1.0 and path == pytest.approx(true_path, rel=scale_tol)
    up_cam = metric[:, :3, :3].transpose(0, 2, 1) @ np.array([0.0, 0.0, 1.0])
    true_up_cam = true_cam[:, :3, :3].transpose(0, 2, 1) @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(np.sum(up_cam * true_up_cam, axis=1), -1, 1))).max() < grav_tol


def test_vi_align_from_given_pims_matches_imu_path() -> None:
    cfg, motion, imu, _, _, times, T_vc = _keyframes(False)
    params = make_params(cfg.imu_noise)
    bias = make_bias(cfg.accel_bias, None)
    pims = [preintegrate(imu, times[k], times[k + 1], params, bias) for k in range(len(times) - 1)]
    a = vi_align(times, T_vc, motion.T_body_cam0, pims=pims)
    assert abs(a.scale / SCALE - 1) < 0.002 and _gravity_err_deg(a) < 0.1
    with pytest.raises(InertialError, match="K-1"):
        vi_align(times, T_vc, motion.T_body_cam0, pims=pims[:-1])
    with pytest.raises(InertialError, match=">= 4 keyframes"):
        vi_align(times[:3], T_vc[:3], motion.T_body_cam0, pims=pims[:2])


def test_ignoring_the_accel_bias_tilts_gravity() -> None:
    """The accel-bias estimate is what brings gravity from ~0.24 deg to ~0 on exact data."""
    cfg, motion, imu, _, _, times, T_vc = _keyframes(False)
    al = vi_align(times, T_vc, motion.T_body_cam0, imu=imu, params=make_params(cfg.imu_noise), accel_bias_sigma=None)
    assert _gravity_err_deg(al) > 0.15 and np.all(al.accel_bias == 0)


def test_spaced_keyframes_keep_the_scale_under_visual_position_noise() -> None:
    """Keyframes 0.1 s apart with 3 mm of position noise: least squares shrinks the scale (errors in variables);
    solving on keyframes >= 0.3 s apart does not, and every keyframe still gets its velocity."""
    cfg, motion, imu, truth = synthetic_imu(4.0, noise=True)
    idx = np.arange(0, len(imu.t), 20)  # 10 keyframes per second
    times = imu.t[idx]
    T_vc = motion.T_world_cam0(times - cfg.start_time)
    T_vc[:, :3, 3] = (T_vc[:, :3, 3] + np.random.default_rng(0).normal(0.0, 0.003, (len(idx), 3))) / SCALE
    params = make_params(cfg.imu_noise)
    dense = vi_align(times, T_vc, motion.T_body_cam0, imu=imu, params=params)
    spaced = vi_align(times, T_vc, motion.T_body_cam0, imu=imu, params=params, min_dt_s=0.3)
    assert dense.scale / SCALE < 0.8, dense.scale  # the bias the subset removes (measured 0.59; spaced 1.003)
    assert abs(spaced.scale / SCALE - 1) < 0.05, spaced.scale
    assert spaced.velocities.shape == (len(idx), 3)
    speed_err = np.abs(np.linalg.norm(spaced.velocities, axis=1) - np.linalg.norm(truth.v_world[idx], axis=1))
    assert np.max(speed_err) < 0.1  # m/s, propagated ones included


def test_spaced_subset_ends_on_the_newest_keyframe() -> None:
    from vslam.inertial.alignment import spaced_subset

    t = np.array([0.0, 0.1, 0.2, 0.35, 0.4, 0.7, 0.75])
    np.testing.assert_array_equal(spaced_subset(t, 0.3), [0, 3, 6])
    np.testing.assert_array_equal(spaced_subset(t[:2], 0.3), [0, 1])
