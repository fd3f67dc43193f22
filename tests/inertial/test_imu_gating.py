"""IMU data is checked before it is believed (issue 39): the sample gate (range, Hampel spike test), the online
buffer that applies it, and stereo-inertial SLAM on EuRoC V1_01 with corrupted copies of imu0/data.csv (spikes,
data ending early, a corrupt stretch and a hole); the end-to-end tests skip without ../shared/data."""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
import pytest

from vslam.config import parse_overrides
from vslam.data.types import ImuSamples
from vslam.inertial.buffer import ImuBuffer
from vslam.inertial.config import InertialConfig
from vslam.inertial.gate import OK, RANGE, SPIKE, _nanmedian_last, gate_reasons, hampel_outliers, range_outliers
from vslam.paths import data_root

CONFIG = "configs/euroc_stereo_inertial.yaml"
G = 9.80665


def _vibrating_imu(n: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """200 Hz (t, gyro, accel) of a hovering MAV: slow motion, rotor vibration (several tones near and above
    Nyquist, so aliased) at EuRoC's amplitudes (|x - local median| up to ~6 m/s^2), white noise; and from
    sample 2000 a car-like pothole, a 2 g 12 Hz oscillation decaying over 0.3 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.005
    slow = np.stack([np.sin(0.7 * t), np.cos(0.5 * t), 0.3 * np.sin(1.3 * t)], axis=1)
    vib = sum(a * np.sin(2 * np.pi * f * t[:, None] + p) for a, f, p in
              ((2.0, 73.0, 0.3), (1.5, 91.0, 1.1), (1.0, 147.0, 2.0), (0.8, 38.0, 0.5)))
    accel = np.array([0.0, 0.0, G]) + slow + vib + 0.8 * rng.standard_normal((n, 3))
    gyro = 0.3 * slow + 0.05 * vib + 0.02 * rng.standard_normal((n, 3))
    k = np.arange(n - 2000)
    accel[2000:, 2] += 2 * G * np.exp(-k * 0.005 / 0.1) * np.sin(2 * np.pi * 12.0 * k * 0.005)
    return t, gyro, accel


def test_nanmedian_matches_numpy() -> None:
    rng = np.random.default_rng(1)
    w = rng.standard_normal((50, 3, 11))
    w[rng.random(w.shape) < 0.3] = np.nan
    w[0, 0, :] = np.nan
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        ref = np.nanmedian(w, axis=2)
    np.testing.assert_allclose(_nanmedian_last(w), ref, equal_nan=True)


def test_range_rejects_readings_at_or_beyond_full_scale() -> None:
    x = np.array([[0.0, 0.0, 9.8], [156.9, 0.0, 0.0], [0.0, -157.0, 0.0], [0.0, 0.0, 1e6], [np.nan, 0.0, 0.0],
                  [156.8, -156.8, 0.0]])
    assert range_outliers(x, 156.9).tolist() == [False, True, True, True, True, False]
    cfg = InertialConfig()
    gyro = np.zeros((3, 3))
    gyro[1, 2] = np.radians(2000.0) + 1e-9  # beyond the default 2000 deg/s
    accel = np.tile([0.0, 0.0, G], (3, 1))
    accel[2, 0] = 17 * G  # beyond the default 16 g
    assert gate_reasons(gyro, accel, cfg).tolist() == [OK, RANGE, RANGE]


def test_spikes_are_removed_and_vibration_is_kept() -> None:
    t, gyro, accel = _vibrating_imu()
    cfg = InertialConfig()
    assert not gate_reasons(gyro, accel, cfg).any()  # vibration and the pothole pass
    accel[[500, 1500, 2010], [0, 1, 2]] = 150.0  # within the 16 g range: only the spike test can see them
    accel[3000, 2] = 1e6
    accel[[2500, 2501, 2502], 0] = -120.0  # a 3-sample burst: still a spike for a 5-sample window
    gyro[3500, 1] = 20.0  # rad/s, within 2000 deg/s
    reasons = gate_reasons(gyro, accel, cfg)
    assert np.flatnonzero(reasons == SPIKE).tolist() == [500, 1500, 2010, 2500, 2501, 2502, 3500]
    assert np.flatnonzero(reasons == RANGE).tolist() == [3000]
    # the floor is what keeps quiet stretches safe: without it, the MAD test alone flags plain noise
    quiet = 0.03 * np.random.default_rng(2).standard_normal((4000, 3))
    assert hampel_outliers(quiet, 5, 3.0, 0.0).sum() > 0
    assert hampel_outliers(quiet, 5, 3.0, cfg.spike_floor_accel).sum() == 0


def test_clean_euroc_imu_passes_the_gate(euroc_v101: Path) -> None:
    from vslam.data.euroc import read_imu_csv
    from vslam.pipeline import PipelineConfig

    imu, _ = read_imu_csv(euroc_v101 / "mav0/imu0/data.csv")
    cfg = PipelineConfig.load(CONFIG).slam.inertial.imu
    assert len(imu) == 29120
    assert not gate_reasons(imu.gyro, imu.accel, cfg).any()  # all 29,120 samples, rotor vibration included
    assert not gate_reasons(imu.gyro, imu.accel, InertialConfig()).any()  # the generic defaults too


def _feed(buf: ImuBuffer, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, chunk: int = 10) -> None:
    lines = np.arange(len(t)) + 2  # a header line, then one line per sample
    for i in range(0, len(t), chunk):
        s = slice(i, i + chunk)
        buf.add(ImuSamples(t[s], gyro[s], accel[s], "imu0/data.csv", lines[s]))
        buf.trim(t[i] - 1.0)


def test_buffer_decides_online_as_the_gate_does_offline() -> None:
    t, gyro, accel = _vibrating_imu()
    accel[[500, 1500], [0, 1]] = 150.0
    accel[3000, 2] = 1e6
    buf = ImuBuffer(InertialConfig())
    _feed(buf, t[:1005], gyro[:1005], accel[:1005])
    assert 500 * 0.005 not in buf.t  # rejected as soon as it arrived (the prediction never sees it)
    assert buf.stats.rejected == {"spike": 1}  # counted once final
    _feed(buf, t[1005:], gyro[1005:], accel[1005:])
    st = buf.finish()
    assert st.seen == 4000 and st.rejected == {"spike": 2, "range": 1}
    assert st.first_line == 502 and st.first_reason == "spike"
    assert "3 of 4000 IMU samples rejected" in st.describe() and "imu0/data.csv line 502" in st.describe()
    assert len(buf.upto(t[-1]).t) < 1000  # trimmed as it went


def test_buffer_says_why_a_stretch_is_not_covered() -> None:
    t, gyro, accel = _vibrating_imu(400)
    cfg = InertialConfig()
    keep = (t < 0.5) | (t > 0.6)  # a 0.1 s hole
    buf = ImuBuffer(cfg)
    buf.add(ImuSamples(t[keep], gyro[keep], accel[keep]))
    assert buf.covers(None, 0.2, cfg.max_gap_s) == (True, "")
    assert buf.covers(0.2, 0.25, cfg.max_gap_s) == (True, "")
    ok, why = buf.covers(0.45, 0.65, cfg.max_gap_s)
    assert not ok and "gap" in why
    ok, why = buf.covers(1.9, 2.1, cfg.max_gap_s)
    assert not ok and why.startswith("no IMU samples after t=1.995")
    accel[(t > 1.0) & (t < 1.2), 2] = 1e6  # all rejected: not covered either
    buf = ImuBuffer(cfg)
    buf.add(ImuSamples(t, gyro, accel))
    ok, why = buf.covers(0.95, 1.25, cfg.max_gap_s)
    assert not ok and "rejected (range)" in why


# ----------------------------------------------------------------------------- end to end on EuRoC V1_01

MAX_FRAMES = 70  # 3.45 s: the 2 s static initialisation, then 1.45 s of IMU prediction and VI BA


def _subset() -> Path:
    p = data_root() / "euroc/V1_01_easy_micro"
    if not p.exists():
        pytest.skip(f"real data not found at {p} (set VSLAM_DATA to the folder holding tum/, kitti/, euroc/)")
    return p


def _copy(src: Path, dst: Path, edit) -> Path:
    """``dst``: the sequence with every folder symlinked but imu0/data.csv, written as ``edit(lines, t_rel)`` returns
    it (lines with their newline, header first; t_rel (N,) s of the samples after the first image)."""
    mav0 = dst / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    for name in os.listdir(src / "mav0"):
        if name != "imu0":
            os.symlink(src / "mav0" / name, mav0 / name)
    os.symlink(src / "mav0/imu0/sensor.yaml", mav0 / "imu0/sensor.yaml")
    lines = (src / "mav0/imu0/data.csv").read_text().splitlines(keepends=True)
    with open(src / "mav0/cam0/data.csv") as f:
        t_img = int(next(line for line in f if not line.startswith("#")).split(",")[0])
    t_rel = np.array([int(line.split(",", 1)[0]) - t_img for line in lines[1:]]) * 1e-9
    keep = 1 + int(np.searchsorted(t_rel, 6.0))  # the images span 4.7 s: later rows only cost parsing time
    (mav0 / "imu0/data.csv").write_text("".join(edit(lines[:keep], t_rel[: keep - 1])))
    return dst


def _set(lines: list[str], i: int, col: int, value: float) -> None:
    f = lines[i].rstrip("\n").split(",")
    f[col] = repr(value)
    lines[i] = ",".join(f) + "\n"


def _run(seq: Path, out: Path):
    from vslam.pipeline import Pipeline, PipelineConfig

    # no plots, no report, the front end on a thread (a child process's start costs more than it saves here):
    # the same trajectory, sooner
    cfg = PipelineConfig.load(CONFIG, parse_overrides([f"dataset.path={seq}", f"dataset.max_frames={MAX_FRAMES}",
                                                       "eval.plots=false", "output.report=false",
                                                       "runtime.frontend_process=false"]))
    return Pipeline(cfg).run(out_dir=out)


def _ate(res) -> float:
    return float(res.eval.ate.translation.rmse)


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    src = _subset()
    base = tmp_path_factory.mktemp("clean")
    res = _run(_copy(src, base / "seq", lambda lines, t: lines), base / "out")
    assert all(s["status"] == "tracked" and s["imu"] == "used" for s in res.stats)
    return res


SPIKES = ((2.5, 4), (2.9, 5), (3.3, 6))  # (s after the first image, accel column): after static init, when the
# IMU predicts and is in the BA; the first lands on a keyframe's sample


@pytest.mark.parametrize("value", [150.0, 1e6])
def test_euroc_imu_spikes_are_rejected(value, clean_run, tmp_path, caplog) -> None:
    src = _subset()
    rows: list[int] = []

    def spikes(lines, t_rel):
        for t, col in SPIKES:
            i = 1 + int(np.searchsorted(t_rel, t))
            _set(lines, i, col, value)
            rows.append(i + 1)  # 1-based line number
        return lines

    seq = _copy(src, tmp_path / "seq", spikes)
    with caplog.at_level(logging.WARNING):
        res = _run(seq, tmp_path / "out")
    assert [s["status"] for s in res.stats] == ["tracked"] * MAX_FRAMES
    assert all(s["imu"] == "used" for s in res.stats)  # three samples dropped: no stretch is off
    assert _ate(res) <= 1.5 * _ate(clean_run)  # measured: 0.0008 m for both and for the clean run
    gate = [r.getMessage() for r in caplog.records if "IMU samples rejected" in r.getMessage()]
    reason = "spike" if value < 176.5 else "range"  # EuRoC's ADIS16448: 18 g full scale
    assert len(gate) == 1 and "3 of " in gate[0] and f"(3 {reason})" in gate[0]
    assert f"data.csv line {rows[0]} " in gate[0]


def test_euroc_imu_ending_early_turns_inertial_off(clean_run, tmp_path, caplog) -> None:
    src = _subset()
    seq = _copy(src, tmp_path / "seq", lambda lines, t_rel: lines[: 1 + int(np.searchsorted(t_rel, 1.5))])
    with caplog.at_level(logging.WARNING):
        res = _run(seq, tmp_path / "out")
    assert [s["status"] for s in res.stats] == ["tracked"] * MAX_FRAMES
    t_rel = np.array([s["timestamp"] for s in res.stats]) - res.stats[0]["timestamp"]
    imu = np.array([s["imu"] for s in res.stats])
    assert (imu[t_rel <= 1.5] == "used").all() and (imu[t_rel > 1.55] == "off").all()
    assert _ate(res) <= 1.5 * _ate(clean_run)
    ends = [r.getMessage() for r in caplog.records if "IMU data ends" in r.getMessage()]
    assert len(ends) == 1 and 1.49 <= float(re.search(r"\(([\d.]+) s into the sequence\)", ends[0]).group(1)) <= 1.5
    assert sum("IMU off at" in r.getMessage() for r in caplog.records) == 1


def test_euroc_corrupt_stretch_then_hole(clean_run, tmp_path, caplog) -> None:
    """A +5 m/s^2 offset over 0.3 s (smooth: the sample gate passes it) is caught by the IMU factor's consistency
    test in the VI BA, then a 0.15 s hole turns the inertial side off; the IMU chain restarts at the keyframe after."""
    src = _subset()

    def corrupt(lines, t_rel):
        for i in np.flatnonzero((t_rel >= 2.05) & (t_rel < 2.35)):
            _set(lines, i + 1, 4, float(lines[i + 1].split(",")[4]) + 5.0)
        return [ln for ln, t in zip(lines, np.r_[-1.0, t_rel]) if not 2.6 <= t < 2.75]

    seq = _copy(src, tmp_path / "seq", corrupt)
    with caplog.at_level(logging.INFO):
        res = _run(seq, tmp_path / "out")
    msgs = [r.getMessage() for r in caplog.records]
    assert [s["status"] for s in res.stats] == ["tracked"] * MAX_FRAMES
    assert _ate(res) <= 1.5 * _ate(clean_run)
    assert any("disagrees with vision" in m for m in msgs)
    assert sum("IMU off at" in m for m in msgs) == 1 and not any("IMU data ends" in m for m in msgs)
    assert sum("IMU chain restarted" in m for m in msgs) == 1
    t_rel = np.array([s["timestamp"] for s in res.stats]) - res.stats[0]["timestamp"]
    imu = np.array([s["imu"] for s in res.stats])
    assert (imu[(t_rel > 2.6) & (t_rel < 2.75)] == "off").all() and (imu[t_rel > 3.01] == "used").all()
