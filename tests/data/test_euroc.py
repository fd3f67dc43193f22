"""EuRoC / TUM-VI (ASL layout) reader: sensor.yaml, stereo pairing, IMU slices, body->cam0 ground truth, bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.data.euroc import EurocSequence, read_camera_yaml
from vslam.errors import DatasetError

H, W = 6, 8
T0 = 1_403_715_273_262_142_976  # ns, the first V1_01 frame
DT_CAM = 50_000_000  # 20 Hz
DT_IMU = 5_000_000  # 200 Hz
T_BS0 = [0.0, -1.0, 0.0, -0.02, 1.0, 0.0, 0.0, -0.06, 0.0, 0.0, 1.0, 0.01, 0.0, 0.0, 0.0, 1.0]
T_BS1 = [0.0, -1.0, 0.0, -0.02, 1.0, 0.0, 0.0, 0.04, 0.0, 0.0, 1.0, 0.01, 0.0, 0.0, 0.0, 1.0]

CAM_YAML = """%YAML:1.0
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam{i}

T_BS:
  cols: 4
  rows: 4
  data: {T}
rate_hz: 20
resolution: [{w}, {h}]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: {model}
distortion_coefficients: {coeffs}
"""

IMU_YAML = """%YAML:1.0
sensor_type: imu
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
accelerometer_noise_density: 2.0000e-3
accelerometer_random_walk: 3.0000e-3
"""


def _cam_yaml(i: int, model: str = "radial-tangential", coeffs: str = "[-0.28, 0.07, 0.0002, 1.8e-05]") -> str:
    # V1_01's intrinsics scaled to the 8x6 images (the principal point must lie inside them)
    return CAM_YAML.format(i=i, T=[T_BS0, T_BS1][i], w=W, h=H, model=model, coeffs=coeffs).replace(
        "458.654, 457.296, 367.215, 248.375", "4.58654, 4.57296, 3.67215, 2.48375")


def make_euroc(root: Path, n: int = 5, cam1_extra: int = 0, imu_before: int = 0) -> Path:
    """root/mav0 with n stereo frames (cam1 lists cam1_extra more, without files), IMU at 200 Hz, 20 Hz ground truth."""
    mav0 = root / "mav0"
    for i in (0, 1):
        cam = mav0 / f"cam{i}"
        (cam / "data").mkdir(parents=True)
        rows = []
        for k in range(n + (cam1_extra if i == 1 else 0)):
            ns = T0 + k * DT_CAM
            rows.append(f"{ns},{ns}.png")
            if k < n:
                cv2.imwrite(str(cam / "data" / f"{ns}.png"), np.full((H, W), 10 * k + i, np.uint8))
        (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "\n".join(rows) + "\n")
        (cam / "sensor.yaml").write_text(_cam_yaml(i))
    imu = mav0 / "imu0"
    imu.mkdir()
    m = (n - 1) * DT_CAM // DT_IMU + 1 + imu_before
    t_imu = [T0 + (k - imu_before) * DT_IMU for k in range(m)]
    rows = [f"{t},0.01,0.02,{0.001 * k},9.81,0.1,-0.2" for k, t in enumerate(t_imu)]
    (imu / "data.csv").write_text("#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z\n" + "\n".join(rows) + "\n")
    (imu / "sensor.yaml").write_text(IMU_YAML)
    gt = mav0 / "state_groundtruth_estimate0"
    gt.mkdir()
    rows = [f"{T0 + k * DT_CAM},{0.1 * k},2.0,1.0,1.0,0.0,0.0,0.0,0.5,0,0,0.001,0.002,0.003,0.01,0.02,0.03" for k in range(n)]
    (gt / "data.csv").write_text("#time(ns),px,py,pz,qw,qx,qy,qz,vx,vy,vz,bwx,bwy,bwz,bax,bay,baz\n" + "\n".join(rows) + "\n")
    return root


@pytest.fixture
def euroc_dir(tmp_path: Path) -> Path:
    return make_euroc(tmp_path / "V9_99_fake")


# ------------------------------------------------------------------------------ real data


@pytest.mark.realdata
def test_real_v101_micro(euroc_v101: Path) -> None:
    seq = EurocSequence(euroc_v101)
    assert len(seq) == 95 and seq.name == "V1_01_easy_micro"  # cam1 lists 4 more images than exist
    calib = seq.calibration
    cam = calib.cam0
    assert (cam.width, cam.height) == (752, 480) and cam.fx == 458.654 and cam.distortion_model == "radtan"
    assert calib.T_body_cam0[0, :4].tolist() == [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
    assert calib.T_body_cam1[1, 3] == 0.0453689425024
    assert calib.baseline == pytest.approx(0.110, abs=0.001)
    assert calib.imu.rate_hz == 200 and calib.imu.gyro_noise_density == 1.6968e-04

    imu = seq.imu()
    assert len(imu) == 29120 and np.median(np.diff(imu.t)) == pytest.approx(0.005, abs=1e-6)
    slices = [len(seq.frame_imu(i)) for i in range(len(seq))]
    assert slices[0] == 1 and all(9 <= s <= 11 for s in slices[1:]) and sum(slices) == pytest.approx(941, abs=5)

    poses = [seq.frame_pose(i) for i in range(len(seq))]
    assert all(p is not None for p in poses)
    pos = np.array([p[:3, 3] for p in poses])
    assert np.linalg.norm(pos - pos[0], axis=1).max() < 0.02  # the MAV barely moves in the first 4.7 s
    body = seq.groundtruth_body()
    assert body.velocity.shape == (len(body.trajectory), 3) and body.accel_bias.shape == body.gyro_bias.shape
    np.testing.assert_allclose(seq.groundtruth().poses[0], body.trajectory.poses[0] @ calib.T_body_cam0)

    f = seq.frame(0)
    assert f.image.shape == (480, 752) and f.image.dtype == np.uint8 and f.right.shape == (480, 752)
    assert len(f.imu) == 1 and f.T_world_cam is not None
    mono = EurocSequence(euroc_v101 / "mav0", sensor="mono")
    assert len(mono) == 95 and mono.calibration.cam1 is None and mono.frame(3).right is None


# ------------------------------------------------------------------------------ content


def test_stereo_frames_imu_and_ground_truth(euroc_dir: Path) -> None:
    seq = EurocSequence(euroc_dir)
    frames = list(seq)
    assert len(frames) == 5 and seq.name == "V9_99_fake"
    f = frames[2]
    assert f.image.shape == (H, W) and f.image[0, 0] == 20 and f.right[0, 0] == 21
    assert f.timestamp == pytest.approx((T0 + 2 * DT_CAM) * 1e-9)
    # IMU: (previous frame, this frame]; 10 samples at 200 Hz over 50 ms, the last one at the frame time.
    assert len(f.imu) == 10 and f.imu.t[-1] == f.timestamp and f.imu.t[0] > frames[1].timestamp
    np.testing.assert_allclose(f.imu.accel[0], [9.81, 0.1, -0.2])
    assert len(frames[0].imu) == 1 and frames[0].imu.t[0] == frames[0].timestamp
    # Ground truth: body at (0.1 k, 2, 1), identity rotation, so T_world_cam0 = T_world_body @ T_BS0.
    T_wb = np.eye(4)
    T_wb[:3, 3] = [0.2, 2.0, 1.0]
    np.testing.assert_allclose(f.T_world_cam, T_wb @ np.array(T_BS0).reshape(4, 4), atol=1e-12)
    body = seq.groundtruth_body()
    np.testing.assert_allclose(body.velocity[0], [0.5, 0, 0])
    np.testing.assert_allclose(body.gyro_bias[0], [0.001, 0.002, 0.003])
    np.testing.assert_allclose(body.accel_bias[0], [0.01, 0.02, 0.03])
    assert seq.calibration.baseline == pytest.approx(0.1)


def test_first_frame_imu_slice_is_empty_without_a_sample_at_its_time(tmp_path: Path) -> None:
    root = make_euroc(tmp_path / "seq", imu_before=3)
    seq = EurocSequence(root)
    assert len(seq.frame_imu(0)) == 1  # the sample at t0; the earlier three are not the frame's
    (root / "mav0" / "imu0" / "data.csv").write_text(
        "#t\n" + "\n".join(f"{T0 + 2_500_000 + k * DT_IMU},0,0,0,0,0,9.8" for k in range(40)) + "\n"
    )
    seq = EurocSequence(root)
    assert len(seq.frame_imu(0)) == 0 and len(seq.frame_imu(1)) == 10


def test_stereo_keeps_frames_listed_by_both_cameras(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = make_euroc(tmp_path / "seq", cam1_extra=3)
    # cam0 loses its frame 1: delete it from its list, so only cam1 has it.
    csv0 = root / "mav0" / "cam0" / "data.csv"
    lines = csv0.read_text().splitlines()
    csv0.write_text("\n".join(lines[:2] + lines[3:]) + "\n")
    with caplog.at_level(logging.INFO, logger="vslam.data.euroc"):
        seq = EurocSequence(root)
    assert len(seq) == 4 and "1 cam1" not in caplog.text and "4 cam1 images have no partner" in caplog.text
    assert [f.image[0, 0] for f in seq] == [0, 20, 30, 40]
    assert [f.right[0, 0] for f in seq] == [1, 21, 31, 41]
    assert len(EurocSequence(root, sensor="mono")) == 4


def test_mav0_path_and_mono_without_cam1(euroc_dir: Path) -> None:
    import shutil

    shutil.rmtree(euroc_dir / "mav0" / "cam1")
    seq = EurocSequence(euroc_dir / "mav0", sensor="mono")
    assert len(seq) == 5 and seq.name == "V9_99_fake" and seq.calibration.cam1 is None
    with pytest.raises(DatasetError, match=r"cam1: missing cam1 \(needed for sensor='stereo'\) folder"):
        EurocSequence(euroc_dir)


def test_equidistant_sensor_yaml_tum_vi(tmp_path: Path) -> None:
    path = tmp_path / "sensor.yaml"
    path.write_text(
        CAM_YAML.format(i=0, T=T_BS0, w=512, h=512, model="equidistant", coeffs="[0.0034, 0.0007, -0.0021, 0.0002]")
        .replace("458.654, 457.296, 367.215, 248.375", "190.978, 190.973, 254.932, 256.897")
    )
    cam, T = read_camera_yaml(path)
    assert cam.distortion_model == "equidistant" and cam.distortion == (0.0034, 0.0007, -0.0021, 0.0002)
    assert (cam.width, cam.height, cam.fx, cam.cy) == (512, 512, 190.978, 256.897)
    np.testing.assert_array_equal(T, np.array(T_BS0).reshape(4, 4))
    assert cam.undistort_points(np.array([[100.0, 100.0]])).shape == (1, 2)


def test_tum_vi_mocap_ground_truth_and_missing_imu_yaml(euroc_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    import shutil

    mav0 = euroc_dir / "mav0"
    shutil.rmtree(mav0 / "state_groundtruth_estimate0")
    (mav0 / "mocap0").mkdir()
    (mav0 / "mocap0" / "data.csv").write_text("#t,px,py,pz,qw,qx,qy,qz\n" + "".join(f"{T0 + k * DT_CAM},{k},0,0,1,0,0,0\n" for k in range(5)))
    (mav0 / "imu0" / "sensor.yaml").unlink()
    with caplog.at_level(logging.WARNING, logger="vslam.data.euroc"):
        seq = EurocSequence(euroc_dir)
    assert seq.groundtruth_body().velocity is None and seq.frame_pose(3)[0, 3] == pytest.approx(3 - 0.02)
    assert seq.calibration.imu.rate_hz == pytest.approx(200.0) and "noise defaults" in caplog.text


# ------------------------------------------------------------------------------ bad input


def _edit(path: Path, lineno: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


def test_missing_folders(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing EuRoC sequence folder"):
        EurocSequence(tmp_path / "nope")
    with pytest.raises(DatasetError, match=r"mav0: missing mav0"):
        EurocSequence(tmp_path)


@pytest.mark.parametrize("rel", ["cam0/data.csv", "cam1/data.csv", "cam0/sensor.yaml"])
def test_missing_files(euroc_dir: Path, rel: str) -> None:
    (euroc_dir / "mav0" / rel).unlink()
    with pytest.raises(DatasetError, match=rf"{rel}: missing"):
        EurocSequence(euroc_dir)


@pytest.mark.parametrize(
    "rel, line, text, message",
    [
        ("cam0/data.csv", 3, f"{T0 + DT_CAM},{T0 + DT_CAM}.png,extra", r"cam0/data.csv:3: expected 2 columns, found 3"),
        ("cam0/data.csv", 3, f"{T0 + DT_CAM}", r"cam0/data.csv:3: expected 2 columns, found 1"),
        ("cam0/data.csv", 3, f"{T0 + DT_CAM}.5,x.png", r"cam0/data.csv:3: timestamp .* is not an integer nanosecond"),
        ("cam0/data.csv", 3, f"{T0},{T0 + DT_CAM}.png", r"cam0/data.csv:3: timestamp .* repeats"),
        ("cam1/data.csv", 4, f"{T0},{T0 + 2 * DT_CAM}.png", r"cam1/data.csv:4: timestamp .* goes back in time"),
        ("cam0/data.csv", 4, f"{T0 + 2 * DT_CAM},gone.png", r"cam0/data.csv:4: listed image .*gone.png does not exist"),
        ("imu0/data.csv", 5, f"{T0 + 3 * DT_IMU},0,0,nan,9.8,0,0", r"imu0/data.csv:5: column 4 is not finite: 'nan'"),
        ("imu0/data.csv", 5, f"{T0 + 3 * DT_IMU},0,0,0,9.8,0", r"imu0/data.csv:5: expected 7 columns, found 6"),
        ("imu0/data.csv", 5, f"{T0 + 3 * DT_IMU},0,0,0,9.8,0,g", r"imu0/data.csv:5: column 7 is not a number"),
        ("imu0/data.csv", 5, f"{T0},0,0,0,9.8,0,0", r"imu0/data.csv:5: timestamp .* goes back in time"),
        ("cam0/sensor.yaml", 13, "intrinsics: [458.654, 457.296, 367.215]", r"cam0/sensor.yaml:13: 'intrinsics' must have 4 numbers, found 3"),
        ("cam0/sensor.yaml", 14, "distortion_model: polynomial", r"cam0/sensor.yaml:14: unknown distortion_model 'polynomial'"),
        ("cam0/sensor.yaml", 15, "distortion_coefficients: [1, 2]", r"cam0/sensor.yaml:15: 'distortion_coefficients' must have 4 or 5 numbers"),
        ("cam0/sensor.yaml", 11, "resolution: [752, 480", r"cam0/sensor.yaml:12: not valid YAML"),
        ("imu0/sensor.yaml", 7, "rate_hz: fast", r"imu0/sensor.yaml:7: 'rate_hz' must be a positive number"),
    ],
)
def test_bad_input_fails_at_open_with_file_and_line(euroc_dir: Path, rel: str, line: int, text: str, message: str) -> None:
    _edit(euroc_dir / "mav0" / rel, line, text)
    with pytest.raises(DatasetError, match=message):
        EurocSequence(euroc_dir)


@pytest.mark.parametrize(
    "line, text, message",
    [
        (2, "1,2,3", r"state_groundtruth_estimate0/data.csv:2: expected 17 columns, found 3"),
        (3, f"{T0 + DT_CAM},0,0,0,0,0,0,0" + ",0" * 9, r"data.csv:3: quaternion \(columns 5-8\) has norm 0, expected unit"),
    ],
)
def test_bad_groundtruth_is_raised_by_groundtruth_not_at_open(euroc_dir: Path, line: int, text: str, message: str) -> None:
    """SLAM does not need the ground truth: a run writes its trajectory, then reports the file's problem."""
    _edit(euroc_dir / "mav0" / "state_groundtruth_estimate0" / "data.csv", line, text)
    seq = EurocSequence(euroc_dir)
    assert next(iter(seq)).T_world_cam is None  # frames carry no ground-truth pose then
    for call in (seq.groundtruth, seq.groundtruth_body):
        with pytest.raises(DatasetError, match=message):
            call()


def test_empty_camera_list(euroc_dir: Path) -> None:
    (euroc_dir / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(DatasetError, match=r"cam0/data.csv: lists no images"):
        EurocSequence(euroc_dir)


def test_T_BS_must_be_rigid(euroc_dir: Path) -> None:
    path = euroc_dir / "mav0" / "cam0" / "sensor.yaml"
    path.write_text(path.read_text().replace("data: [0.0, -1.0", "data: [2.0, -1.0"))
    with pytest.raises(DatasetError, match=r"cam0/sensor.yaml:6: T_BS is not a rigid transform"):
        EurocSequence(euroc_dir)


def test_bad_sensor(euroc_dir: Path) -> None:
    with pytest.raises(DatasetError, match="sensor 'rgbd' not available"):
        EurocSequence(euroc_dir, sensor="rgbd")


def test_undecodable_frame_is_skipped_with_warning(euroc_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    bad = euroc_dir / "mav0" / "cam1" / "data" / f"{T0 + 3 * DT_CAM}.png"
    bad.write_bytes(b"\x89PNG broken")
    seq = EurocSequence(euroc_dir)
    with caplog.at_level(logging.WARNING, logger="vslam.data.euroc"):
        frames = list(seq)
    assert [f.index for f in frames] == [0, 1, 2, 4]
    assert bad.name in caplog.text
    # The frame after the skipped one also gets the skipped frame's IMU samples: no gap in the stream.
    assert len(frames[3].imu) == 20 and frames[3].imu.t[0] > frames[2].timestamp
    assert len(seq.frame_imu(4)) == 10  # random access: samples since the listed predecessor
