"""Kind ``imu_preint``: IMU preintegration error and NEES on real data."""

from __future__ import annotations

import time
from typing import Any


from vslam.bench.suite import BenchRow
from vslam.bench.tables import md_failed_row, md_section
from vslam.childproc import peak_rss_mb


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Inertial: real-IMU preintegration error/NEES from ground-truth states, and the static window (``set``:
    data=<folder under $VSLAM_DATA>, lengths=[...], static_window_s, noise_scale, align_spans=[...])."""
    from vslam.inertial.evaluate import evaluate_euroc_imu
    from vslam.paths import data_root

    t0 = time.perf_counter()
    out = evaluate_euroc_imu(data_root() / str(overrides.get("data", "euroc/V1_01_easy_micro")),
                             tuple(float(x) for x in overrides.get("lengths", (0.5, 1.0, 2.0))),
                             float(overrides.get("static_window_s", 4.0)), float(overrides.get("noise_scale", 1.0)),
                             tuple(float(x) for x in overrides.get("align_spans", (3.0, 5.0, 10.0))))
    return {**out, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Inertial, real-IMU numbers: one line per window length, then the static-window line per row."""
    if not rows:
        return []
    lines = md_section("IMU preintegration on real data",
                       "Windows start at ground-truth states (pose, velocity, biases); error of the predicted end pose; "
                       "NEES of rotation + position against the pim's covariance (6 dof: consistent ≈ 6).",
                       ["row", "window s", "windows", "position RMSE m", "rotation RMSE °", "predicted σ_p m",
                        "NEES mean (median)", "NEES rot / pos", "noise × for NEES 6", "target"])
    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 10))
            continue
        for w in r["windows"]:
            lines.append(f"| {row.name} | {w['length_s']:g} | {w['windows']} | {w['pos_rmse_m']:.4f} | {w['rot_rmse_deg']:.3f} "
                         f"| {w['sigma_pos_median_m']:.4f} | {w['nees_mean']:.0f} ({w['nees_median']:.0f}) "
                         f"| {w['nees_rot_mean']:.0f} / {w['nees_pos_mean']:.0f} | {w['noise_inflation_for_consistency']:.1f} | {row.target} |")
    ident = [(row, r) for row, r in rows if "error" not in r and r.get("identified")]
    if ident:
        lines += ["", "The same windows with an identified noise model (`vslam.inertial.evaluate.fit_noise_model`): white-noise "
                  "densities plus the std of the ground-truth biases' own error, fitted by maximum likelihood on the windows "
                  "of all three lengths that start in the first half of the flight; NEES on the second half (held out). "
                  "Last column: the same fit with the densities only (inflation as VINS-Mono / OKVIS do, no bias term).", "",
                  "| row | gyro density (× sensor.yaml) | accel density (×) | σ of GT gyro / accel bias | window s "
                  "| held-out windows | NEES mean (median) | NEES rot / pos | share < χ²₆ 95 % | densities-only fit: NEES |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for row, r in ident:
            d, m = r["identified"], r["identified"]["model"]
            for w in d["held_out"]:
                lines.append(f"| {row.name} | {m['gyro_noise_density']:.2e} ({d['gyro_density_x_datasheet']:.1f}) "
                             f"| {m['accel_noise_density']:.2e} ({d['accel_density_x_datasheet']:.1f}) "
                             f"| {m['gyro_bias_sigma']:.1e} rad/s / {m['accel_bias_sigma']:.3f} m/s² | {w['length_s']:g} "
                             f"| {w['windows']} | {w['nees_mean']:.1f} ({w['nees_median']:.1f}) "
                             f"| {w['nees_rot_mean']:.1f} / {w['nees_pos_mean']:.1f} | {100 * w['frac_nees_below_chi2_95']:.0f} % "
                             f"| {w['nees_mean_white_only']:.1f} |")
    for row, r in rows:
        if "error" not in r:
            st = r["static"]
            lines.append("")
            lines.append(f"{row.name}, static window {st['window_s']:g} s (still: {'yes' if st['still'] else 'no'}): gravity "
                         f"direction {st['gravity_dir_err_deg']:.2f}° from ground truth ({st['gravity_dir_err_gt_accel_bias_deg']:.2f}° "
                         f"with the ground-truth accel bias as prior); gyro bias error {st['gyro_bias_err_rad_s']:.4f} rad/s "
                         f"(ground-truth bias {st['gyro_bias_gt_norm_rad_s']:.4f} rad/s).")
    aligned = [(row, r) for row, r in rows if "error" not in r and r.get("alignment")]
    if aligned:
        lines += ["", "Visual-inertial alignment (`vi_align`) on ground-truth camera poses hidden behind a similarity "
                  "(scale 3.7, tilted frame), keyframes every 0.25 s, zero starting biases:", "",
                  "| row | span s | windows | scale error % median / max | gravity error ° median / max | gyro bias error rad/s |",
                  "|---|---|---|---|---|---|"]
        for row, r in aligned:
            for a in r["alignment"]:
                lines.append(f"| {row.name} | {a['span_s']:g} | {a['windows']} | {a['scale_err_median_pct']:.2f} / "
                             f"{a['scale_err_max_pct']:.2f} | {a['gravity_err_median_deg']:.2f} / {a['gravity_err_max_deg']:.2f} "
                             f"| {a['gyro_bias_err_median_rad_s']:.4f} |")
    return lines
