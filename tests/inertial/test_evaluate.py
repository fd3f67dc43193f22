"""Real EuRoC V1_01 preintegration numbers stay where they were measured (regression band)."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.data.euroc import EurocSequence
from vslam.inertial.evaluate import ground_truth_arrays, window_errors
from vslam.paths import data_root


@pytest.fixture(scope="module")
def v101():
    path = data_root() / "euroc/V1_01_easy_micro"
    if not path.exists():
        pytest.skip(f"real data not found at {path} (set VSLAM_DATA to the folder holding euroc/)")
    seq = EurocSequence(path, sensor="mono")
    return seq.imu(), ground_truth_arrays(seq.groundtruth_body()), seq.calibration.imu


def test_real_one_second_windows(v101) -> None:
    imu, gt, noise = v101
    res = window_errors(imu, *gt, noise=noise, length_s=1.0, stride_s=4.0)
    s = res.summary()
    assert s["windows"] == 36
    # Measured (all 144 windows): 24 mm / 0.125 deg rms, NEES mean 477 against 6 expected. The synthetic
    # test shows the NEES machinery gives ~6 on modelled noise; on EuRoC the errors are ~9x the sensor.yaml
    # noise (ground-truth bias/attitude accuracy and unmodelled vibration effects; see BENCHMARKS.md notes).
    assert 0.015 < s["pos_rmse_m"] < 0.035
    assert 0.08 < s["rot_rmse_deg"] < 0.18
    assert 250 < s["nees_mean"] < 800
    # A 10 ms clock error would roughly double the rotation error: the band above would catch it.
    assert np.all(np.isfinite(res.nees))


def test_real_alignment_on_ground_truth_poses(v101) -> None:
    from vslam.inertial.evaluate import alignment_numbers

    imu, _, noise = v101
    seq = EurocSequence(data_root() / "euroc/V1_01_easy_micro", sensor="mono")
    a = alignment_numbers(imu, seq.groundtruth_body(), seq.calibration.T_body_cam0, noise, span_s=5.0, stride_s=20.0)
    assert a["windows"] == 7
    # Measured (stride 10 s, 14 windows): scale 1.7 % median / 2.9 % max, gravity 0.36 / 1.24 deg. Holding the
    # accel bias fixed gives ~1 deg and 2-3 %: these bands catch a loss of the accel-bias estimate.
    assert a["scale_err_median_pct"] < 2.5 and a["scale_err_max_pct"] < 4.0
    assert a["gravity_err_median_deg"] < 0.6 and a["gravity_err_max_deg"] < 1.5
    assert a["gyro_bias_err_median_rad_s"] < 2.5e-3


def test_real_identified_noise_is_consistent_on_held_out_windows(v101) -> None:
    """Fitted on the first half of the flight, the noise model predicts the second half's errors (NEES ≈ 6)."""
    from vslam.inertial.evaluate import identified_noise_numbers

    imu, _, noise = v101
    seq = EurocSequence(data_root() / "euroc/V1_01_easy_micro", sensor="mono")
    out = identified_noise_numbers(imu, seq.groundtruth_body(), noise)
    # Measured: gyro 4.1x / accel 5.3x the sensor.yaml densities, ground-truth bias error 1.0e-3 rad/s and
    # 0.026 m/s^2; held-out NEES 5.2 / 5.6 / 5.0 at 0.5 / 1 / 2 s (sensor.yaml alone: 324 / 477 / 543).
    assert 2.5 < out["gyro_density_x_datasheet"] < 7 and 3 < out["accel_density_x_datasheet"] < 9
    for w in out["held_out"]:
        assert w["windows"] >= 30
        assert 4.0 < w["nees_mean"] < 8.0, w
        assert w["frac_nees_below_chi2_95"] > 0.9
