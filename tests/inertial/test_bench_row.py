"""The `imu_preint` benchmark row renders its own table (the computation is tested in test_evaluate)."""

from __future__ import annotations

from vslam.bench import BenchRow
from vslam.bench.kinds.inertial import table as _imu_table


def test_imu_table_renders_windows_static_alignment_and_failures() -> None:
    window = {"length_s": 1.0, "windows": 144, "pos_rmse_m": 0.0242, "rot_rmse_deg": 0.125, "sigma_pos_median_m": 0.0024,
              "nees_mean": 477.0, "nees_median": 425.0, "nees_rot_mean": 164.0, "nees_pos_mean": 306.0,
              "noise_inflation_for_consistency": 8.9}
    static = {"window_s": 4.0, "still": True, "gravity_dir_err_deg": 0.58, "gravity_dir_err_gt_accel_bias_deg": 0.21,
              "gyro_bias_err_rad_s": 0.0014, "gyro_bias_gt_norm_rad_s": 0.08}
    align = {"span_s": 5.0, "windows": 14, "scale_err_median_pct": 1.74, "scale_err_max_pct": 2.9,
             "gravity_err_median_deg": 0.36, "gravity_err_max_deg": 1.24, "gyro_bias_err_median_rad_s": 0.001}
    ok = BenchRow("imu", kind="imu_preint", target="NEES ≈ 6")
    bad = BenchRow("imu-bad", kind="imu_preint")
    text = "\n".join(_imu_table([(ok, {"windows": [window], "static": static, "alignment": [align]}),
                                 (bad, {"error": "InertialError: no data"})]))
    assert "| imu | 1 | 144 | 0.0242 | 0.125 | 0.0024 | 477 (425) | 164 / 306 | 8.9 | NEES ≈ 6 |" in text
    assert "gravity direction 0.58°" in text and "(0.21° with the ground-truth accel bias as prior)" in text
    assert "| imu | 5 | 14 | 1.74 / 2.90 | 0.36 / 1.24 | 0.0010 |" in text
    assert "| imu-bad | **failed**: InertialError: no data |" in text
    assert _imu_table([]) == []
