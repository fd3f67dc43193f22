"""The INS/GNSS simulator driven by an external trajectory and the mode choice fed by a vslam-style track
(issue 9: the GNSS-blocked switch on a real vslam trajectory)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vslam.data.trajectory import Trajectory, write_trajectory
from vslam.errors import ConfigError
from vslam.fusion.exp_vslam import R_CAM_BODY, R_NAV_WORLD, VslamValidityConfig, load_run, run_validity_vslam, truth_of
from vslam.fusion.simulate import TrajectoryConfig, drifting_vo_track, mechanize_step, simulate_truth, truth_from_samples
from vslam.geometry.se3 import make_T, so3_exp


def _drive(duration_s: float, rate_hz: float = 10.0):
    """A car-like drive from the simulator, sampled like a camera: (t (K,), p_nav (K, 3), C_b^n (K, 3, 3))."""
    tr = simulate_truth(TrajectoryConfig(duration_s=duration_s, dt_imu=0.01, speed_mps=8.0, turn_period_s=20.0))
    k = np.arange(0, len(tr.t), int(round(1 / (rate_hz * 0.01))))
    return tr.t[k], tr.p[k], tr.C[k], tr


def test_truth_from_samples_reproduces_the_drive_and_its_imu():
    t, p, C, ref = _drive(30.0)
    truth = truth_from_samples(t + 100.0, p, C, 0.01)  # any clock: the truth starts at 0
    assert truth.t[0] == 0.0 and truth.t[-1] == pytest.approx(t[-1])
    # the truth is the mechanisation of its own IMU inputs (what the INS integrates), and follows the samples
    pk, vk, Ck = truth.p[0], truth.v[0], truth.C[0]
    for k in range(len(truth.t) - 1):
        pk, vk, Ck = mechanize_step(pk, vk, Ck, truth.f_b[k], truth.w_b[k], 0.01)
    np.testing.assert_allclose(pk, truth.p[-1], atol=1e-9)
    np.testing.assert_allclose(truth.p[::10], p, atol=5e-3)  # mm: spline vs the simulator's own integration
    np.testing.assert_allclose(truth.C[::10], C, atol=1e-6)
    inner = slice(50, -50)  # the spline's free ends differ from the truth near the start and the end
    np.testing.assert_allclose(truth.w_b[inner], ref.w_b[inner], atol=2e-3)  # rad/s
    np.testing.assert_allclose(truth.f_b[inner], ref.f_b[inner], atol=0.05)  # m/s^2
    with pytest.raises(ValueError, match="increasing time"):
        truth_from_samples(t[::-1], p, C, 0.01)


def _camera_poses(p_nav: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Navigation-frame drive -> T_world_cam in vslam's convention (world = first camera axes)."""
    T = np.repeat(np.eye(4)[None], len(p_nav), 0)
    T[:, :3, :3] = R_NAV_WORLD.T @ C @ R_CAM_BODY.T
    T[:, :3, 3] = (p_nav - p_nav[0]) @ R_NAV_WORLD
    return T


def test_camera_ground_truth_becomes_the_same_drive():
    t, p, C, _ = _drive(20.0)
    truth = truth_of(Trajectory(t, _camera_poses(p, C)), 0.01)
    np.testing.assert_allclose(truth.p[::10], p - p[0], atol=5e-3)
    np.testing.assert_allclose(truth.C[::10], C, atol=1e-6)
    assert truth.v[0][0] > 7.0  # forward (camera +z) is North


def _fake_run(tmp_path, mono: bool, duration_s: float = 40.0):
    """A `vslam run` folder: ground truth of the drive, and an estimate in its own frame (rotated, shifted,
    scaled when monocular) with distance-proportional drift; the first 10 frames untracked (as before a
    monocular initialisation)."""
    t, p, C, _ = _drive(duration_s)
    t = t + 50.0
    gt = _camera_poses(p, C)
    rng = np.random.default_rng(3)
    p_est = drifting_vo_track(t, gt[:, :3, 3], rng, drift_per_m=0.005, noise_m=0.02)
    s = 0.2 if mono else 1.0
    T_est = make_T(so3_exp(np.array([0.3, -1.0, 0.5])), np.array([4.0, -2.0, 1.0]))
    est = gt.copy()
    est[:, :3, 3] = s * p_est @ T_est[:3, :3].T + T_est[:3, 3]
    est[:10] = np.eye(4)
    write_trajectory(tmp_path / "groundtruth.tum.txt", Trajectory(t, gt), "tum")
    write_trajectory(tmp_path / "trajectory.tum.txt", Trajectory(t, est), "tum")
    rows = ["index,timestamp,tracked"] + [f"{i},{ti:.6f},{int(i >= 10)}" for i, ti in enumerate(t)]
    (tmp_path / "stats.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "config.yaml").write_text(f"dataset:\n  sensor: {'mono' if mono else 'rgbd'}\n")
    return tmp_path


def test_load_run_drops_untracked_frames(tmp_path):
    run = load_run(_fake_run(tmp_path, mono=True, duration_s=5.0))
    assert run.monocular and len(run.groundtruth) == 51 and len(run.estimate) == 41
    with pytest.raises(ConfigError, match="no trajectory.tum.txt"):
        load_run(tmp_path / "missing")


@pytest.mark.parametrize("mono", [True, False], ids=["mono-sim3", "metric-se3"])
def test_mode_switch_with_an_external_track(tmp_path, mono):
    run = _fake_run(tmp_path / "run", mono)
    grades = ("tactical", "automotive") if mono else ("tactical",)
    cfg = VslamValidityConfig(vo_drift_per_m=0.005, imu_grades=grades)  # the VIO variance model matches the track's drift
    m = run_validity_vslam(tmp_path / "out", seed=0, run_dir=run, cfg=cfg)
    assert json.loads((tmp_path / "out" / "metrics.json").read_text()) == m
    assert "VIO" in m["headline"] and (tmp_path / "out" / "mode_choice.png").is_file()
    o = m["ours"]
    assert set(o["by_imu"]) == set(grades) and "per IMU grade" in (tmp_path / "out" / "report.md").read_text()
    if mono:  # a worse IMU drifts further while GNSS is blocked (measured 6.03 vs 2.74 m); the visual modes do not care
        auto = o["by_imu"]["automotive"]["rms_gnss_blocked"]
        assert auto["GNSS+INS"] > 1.5 * o["rms_gnss_blocked"]["GNSS+INS"]
        assert (tmp_path / "out" / "automotive" / "report.md").is_file()
    blk = o["rms_gnss_blocked"]
    assert o["blocked_epochs"] == pytest.approx(0.4 * 400, abs=2)  # 16 s of the 40 s drive at 10 Hz (401 frames, 10 untracked)
    # every epoch with >= 4 satellites before the blockage, inside the track: measured 150
    assert o["vo_align_epochs"] >= 140 and o["tracked_frames"] == 391
    # aligned from GNSS/INS alone (no truth): measured VIO 1.40 (Sim3) / 1.74 (SE3) m vs GNSS+INS 2.74 m
    assert blk["VIO"] < 0.8 * blk["GNSS+INS"]
    # r_opt follows the visual modes while GNSS is blocked: measured 1.05 / 1.12 m, 91 % VIO+GNSS
    assert blk["r_opt"] < 0.5 * blk["GNSS+INS"] and blk["r_opt"] <= blk["VIO"]
    assert o["mode_share_blocked"]["GNSS+INS"] < 0.25


def test_unknown_imu_grade(tmp_path):
    with pytest.raises(ConfigError, match="imu_grades"):
        run_validity_vslam(tmp_path / "out", run_dir=_fake_run(tmp_path / "run", True, 5.0), cfg=VslamValidityConfig(imu_grades=("nope",)))
