"""TUM RGB-D reader: association, calibration, depth units, ground truth, extras and every bad-input path."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.data.tum import ROS_DEFAULT_CAMERA, TUM_CAMERAS, TumRgbdSequence, associate
from vslam.errors import DatasetError

H, W = 480, 640  # the freiburg cameras' size: the reader skips an image of another size than its camera


def _write_list(path: Path, header: str, rows: list[str]) -> None:
    path.write_text(f"# {header}\n# timestamp filename\n" + "".join(r + "\n" for r in rows))


def make_tum(
    root: Path,
    n: int = 5,
    *,
    t0: float = 100.0,
    dt: float = 0.033,
    depth_offset: float = 0.001,
    gt_from: float | None = None,
) -> Path:
    """A tiny TUM folder: n rgb (HxW BGR) and n depth (uint16, depth 1 m + 0.1 m * i), 100 Hz ground truth."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_rows, depth_rows = [], []
    for i in range(n):
        t = t0 + i * dt
        img = np.full((H, W, 3), (10 * i, 20, 30), np.uint8)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), img)
        cv2.imwrite(str(root / "depth" / f"{t + depth_offset:.6f}.png"), np.full((H, W), 5000 + 500 * i, np.uint16))
        rgb_rows.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_rows.append(f"{t + depth_offset:.6f} depth/{t + depth_offset:.6f}.png")
    _write_list(root / "rgb.txt", "color images", rgb_rows)
    _write_list(root / "depth.txt", "depth maps", depth_rows)
    start = t0 if gt_from is None else gt_from
    gt = [f"{start + k * 0.01:.4f} {0.01 * k:.4f} 0 0 0 0 0 1" for k in range(int((t0 + n * dt - start) / 0.01) + 2)]
    (root / "groundtruth.txt").write_text("# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    return root


@pytest.fixture
def tum_dir(tmp_path: Path) -> Path:
    return make_tum(tmp_path / "rgbd_dataset_freiburg1_fake")


# ------------------------------------------------------------------------------ real data


@pytest.mark.realdata
def test_real_teddy(tum_teddy: Path) -> None:
    mono = TumRgbdSequence(tum_teddy, sensor="mono")
    assert len(mono) == 200
    assert sum(mono.frame_pose(i) is not None for i in range(len(mono))) == 196
    assert all(mono.frame_pose(i) is None for i in range(4))  # ground truth starts after frame 3

    seq = TumRgbdSequence(tum_teddy)
    cam = seq.calibration.cam0
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (535.4, 539.2, 320.1, 247.6)
    assert cam.distortion_model == "none" and seq.calibration.depth_scale == 5000.0
    # Every rgb image is a frame; the depth stream drops 7 (nearest depth 29-32 ms away): those get depth=None.
    assert len(seq) == 200
    assert sum(seq.frame_pose(i) is not None for i in range(len(seq))) == 196
    assert sum(d is None for d in seq._depth) == 7
    assert len(seq.groundtruth()) > 600 and seq.accelerometer() is None
    f = seq.frame(20)
    assert f.image.shape == (480, 640, 3) and f.image.dtype == np.uint8
    assert f.depth.dtype == np.float32 and f.depth.shape == (480, 640)
    assert 0.5 < float(np.median(f.depth[f.depth > 0])) < 3.0
    assert f.T_world_cam is not None and f.imu is None and f.timestamp == seq.timestamps()[20]


# ------------------------------------------------------------------------------ association


def _associate_py(a: list[float], b: list[float], max_diff: float) -> list[tuple[int, int]]:
    """TUM associate.py, transcribed (all pairs, sort, greedy)."""
    cand = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) < max_diff)
    ua, ub, out = set(), set(), []
    for _, i, j in cand:
        if i not in ua and j not in ub:
            ua.add(i)
            ub.add(j)
            out.append((i, j))
    return sorted(out)


def test_associate_is_greedy_one_to_one() -> None:
    ia, ib = associate(np.array([0.0, 0.01]), np.array([0.006]), 0.02)
    assert ia.tolist() == [1] and ib.tolist() == [0]  # the closer rgb wins, the other goes unmatched


def test_associate_matches_reference_on_random_streams() -> None:
    rng = np.random.default_rng(0)
    a = np.sort(rng.uniform(0, 3, 90))
    b = np.sort(rng.uniform(0, 3, 80))
    ia, ib = associate(a, b, 0.02)
    assert list(zip(ia.tolist(), ib.tolist())) == _associate_py(a.tolist(), b.tolist(), 0.02)


def test_max_diff_is_configurable(tmp_path: Path) -> None:
    root = make_tum(tmp_path / "rgbd_dataset_freiburg3_x", depth_offset=0.015)
    assert all(f.depth is not None for f in TumRgbdSequence(root))
    # no depth within 10 ms: an RGB-D run would have no depth at all, which is an error, not 5 empty frames
    with pytest.raises(DatasetError, match=r"depth.txt: no rgb image has a depth image within 0.01 s .*--sensor mono"):
        TumRgbdSequence(root, max_diff=0.01)
    assert all(f.depth is None for f in TumRgbdSequence(root, max_diff=0.01, sensor="mono"))


# ------------------------------------------------------------------------------ content


def test_frames_depth_in_metres_and_ground_truth(tum_dir: Path) -> None:
    seq = TumRgbdSequence(tum_dir)
    frames = list(seq)
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert frames[0].image.shape == (H, W, 3) and frames[0].image.dtype == np.uint8
    assert frames[0].image[0, 0, 0] == 0 and frames[2].image[0, 0, 0] == 20  # BGR order kept
    np.testing.assert_allclose(frames[2].depth, 1.2, rtol=1e-6)
    assert frames[2].depth.dtype == np.float32
    assert frames[3].T_world_cam is not None
    assert frames[3].T_world_cam[0, 3] == pytest.approx(0.10, abs=0.011)  # gt x = 0.01 * k at 100 Hz
    np.testing.assert_allclose(seq.timestamps(), 100.0 + 0.033 * np.arange(5))
    assert frames[0].dynamic_mask is None and frames[0].boxes is None


def test_zero_depth_stays_invalid(tum_dir: Path) -> None:
    name = (tum_dir / "depth.txt").read_text().splitlines()[2].split()[1]
    raw = np.zeros((H, W), np.uint16)
    raw[0, 0] = 10000
    cv2.imwrite(str(tum_dir / name), raw)
    d = TumRgbdSequence(tum_dir).frame(0).depth
    assert d[0, 0] == 2.0 and d[1, 1] == 0.0


def test_no_ground_truth_before_it_starts(tmp_path: Path) -> None:
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_x", gt_from=100.08)
    seq = TumRgbdSequence(root)
    assert [seq.frame_pose(i) is None for i in range(5)] == [True, True, False, False, False]


@pytest.mark.parametrize("name, key", [("rgbd_dataset_freiburg1_fake", "freiburg1"), ("rgbd_dataset_freiburg2_desk", "freiburg2"), ("fr3_walking", "freiburg3")])
def test_camera_from_folder_name(tmp_path: Path, name: str, key: str) -> None:
    cam = TumRgbdSequence(make_tum(tmp_path / name)).calibration.cam0
    assert cam is TUM_CAMERAS[key]
    if key == "freiburg1":
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (517.3, 516.5, 318.6, 255.3)
        assert cam.distortion_model == "radtan" and cam.distortion == (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


def test_unknown_camera_uses_ros_default_with_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="vslam.data.tum"):
        seq = TumRgbdSequence(make_tum(tmp_path / "my_recording"))
    assert seq.calibration.cam0 is ROS_DEFAULT_CAMERA
    assert "ROS default" in caplog.text


def test_calibration_yaml_overrides(tum_dir: Path) -> None:
    (tum_dir / "calibration.yaml").write_text(
        "width: 640\nheight: 480\nfx: 100.0\nfy: 101.0\ncx: 4.0\ncy: 3.0\ndistortion_model: none\ndistortion: []\ndepth_scale: 1000\n"
    )
    seq = TumRgbdSequence(tum_dir)
    cam = seq.calibration.cam0
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (640, 480, 100.0, 101.0, 4.0, 3.0)
    assert cam.distortion_model == "none" and not cam.is_distorted
    assert seq.calibration.depth_scale == 1000.0
    np.testing.assert_allclose(seq.frame(0).depth, 5.0)


def test_calibration_yaml_unknown_key_names_line(tum_dir: Path) -> None:
    (tum_dir / "calibration.yaml").write_text("fx: 100.0\nfocal: 3\n")
    with pytest.raises(DatasetError, match=r"calibration.yaml:2: unknown key 'focal'"):
        TumRgbdSequence(tum_dir)


def test_calibration_yaml_bad_value(tum_dir: Path) -> None:
    (tum_dir / "calibration.yaml").write_text("fx: fast\n")
    with pytest.raises(DatasetError, match=r"calibration.yaml:1: 'fx' must be a positive number"):
        TumRgbdSequence(tum_dir)


def test_accelerometer_is_exposed_not_put_in_frames(tum_dir: Path) -> None:
    (tum_dir / "accelerometer.txt").write_text("# accelerometer data\n100.0 0.1 -9.8 0.2\n100.05 0.0 -9.7 0.1\n")
    seq = TumRgbdSequence(tum_dir)
    t, acc = seq.accelerometer()
    np.testing.assert_allclose(t, [100.0, 100.05])
    np.testing.assert_allclose(acc[0], [0.1, -9.8, 0.2])
    assert seq.imu() is None and seq.frame(0).imu is None


def test_mask_and_boxes(tum_dir: Path) -> None:
    (tum_dir / "mask").mkdir()
    m = np.zeros((H, W), np.uint8)
    m[1:3, 2:5] = 255
    cv2.imwrite(str(tum_dir / "mask" / "100.033000.png"), m)
    (tum_dir / "mask.txt").write_text("# t filename\n100.033000 mask/100.033000.png\n")
    (tum_dir / "boxes.txt").write_text("# t id x1 y1 x2 y2\n100.033 7 2 1 5 3\n100.033 9 0 0 1 1\n100.099 7 3 1 6 3\n")
    frames = list(TumRgbdSequence(tum_dir))
    assert frames[0].dynamic_mask is None
    mask = frames[1].dynamic_mask
    assert mask.dtype == bool and mask.sum() == 6 and mask[1, 2] and not mask[0, 0]
    np.testing.assert_array_equal(frames[1].boxes, [[2, 1, 5, 3], [0, 0, 1, 1]])
    assert frames[0].boxes.shape == (0, 4) and frames[3].boxes.shape == (1, 4)


def test_mono_needs_no_depth(tum_dir: Path) -> None:
    (tum_dir / "depth.txt").unlink()
    seq = TumRgbdSequence(tum_dir, sensor="mono")
    assert len(seq) == 5 and seq.frame(0).depth is None and seq.calibration.depth_scale is None


# ------------------------------------------------------------------------------ bad input


def _replace_line(path: Path, lineno: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing TUM RGB-D sequence folder"):
        TumRgbdSequence(tmp_path / "nope")


@pytest.mark.parametrize("name", ["rgb.txt", "depth.txt"])
def test_missing_list(tum_dir: Path, name: str) -> None:
    (tum_dir / name).unlink()
    with pytest.raises(DatasetError, match=rf"{name}: missing {name}"):
        TumRgbdSequence(tum_dir)


@pytest.mark.parametrize(
    "file, line, text, message",
    [
        ("rgb.txt", 4, "100.033000 rgb/100.033000.png extra", r"rgb.txt:4: expected 2 columns, found 3"),
        ("depth.txt", 3, "100.001000", r"depth.txt:3: expected 2 columns, found 1"),
        ("rgb.txt", 5, "abc rgb/100.066000.png", r"rgb.txt:5: column 1 is not a number: 'abc'"),
        ("rgb.txt", 5, "nan rgb/100.066000.png", r"rgb.txt:5: column 1 is not finite"),
        ("rgb.txt", 5, "100.033000 rgb/100.033000.png", r"rgb.txt:5: timestamp .* repeats"),
        ("depth.txt", 5, "99.0 depth/100.067000.png", r"depth.txt:5: timestamp .* goes back in time"),
        ("rgb.txt", 6, "100.099000 rgb/missing.png", r"rgb.txt:6: listed file .*missing.png does not exist"),
    ],
)
def test_bad_tables_fail_at_open_with_file_and_line(tum_dir: Path, file: str, line: int, text: str, message: str) -> None:
    _replace_line(tum_dir / file, line, text)
    with pytest.raises(DatasetError, match=message):
        TumRgbdSequence(tum_dir)


@pytest.mark.parametrize(
    "line, text, message",
    [
        (4, "100.01 0 0 0 0 0 0", r"groundtruth.txt:4: expected 8 columns, found 7"),
        (5, "100.02 x 0 0 0 0 0 1", r"groundtruth.txt:5: column 2 is not a number"),
        (5, "100.02 0 0 0 nan 0 0 1", r"groundtruth.txt:5: column 5 is not finite"),
        (5, "100.02 0 0 0 0 0 0 0", r"groundtruth.txt:5: quaternion \(columns 5-8\) has norm 0, expected unit"),
        (5, "100.02 0 0 0 0 0 0 5.2", r"groundtruth.txt:5: quaternion .* has norm 5.2,"),
        (5, "100.02 0 0 0 0 0 0 1.002", r"groundtruth.txt:5: quaternion .* has norm 1.002,"),
    ],
)
def test_bad_groundtruth_is_raised_by_groundtruth_not_at_open(tum_dir: Path, line: int, text: str, message: str) -> None:
    """SLAM does not need the ground truth: a run writes its trajectory, then reports the file's problem."""
    _replace_line(tum_dir / "groundtruth.txt", line, text)
    seq = TumRgbdSequence(tum_dir)
    assert seq.frame(0).T_world_cam is None
    with pytest.raises(DatasetError, match=message):
        seq.groundtruth()


def test_rgb_image_of_another_size_is_blamed_not_its_depth(tum_dir: Path, caplog) -> None:
    cv2.imwrite(str(tum_dir / "rgb" / "100.033000.png"), np.zeros((240, 320, 3), np.uint8))
    frames = list(TumRgbdSequence(tum_dir))
    assert [f.index for f in frames] == [0, 2, 3, 4]
    assert "rgb/100.033000.png: image is 320x240, the camera's is 640x480; frame skipped" in caplog.text
    assert "depth" not in caplog.text


def test_empty_rgb_list(tum_dir: Path) -> None:
    (tum_dir / "rgb.txt").write_text("# color images\n")
    with pytest.raises(DatasetError, match=r"rgb.txt: lists no images"):
        TumRgbdSequence(tum_dir)


def test_bad_optional_tables(tum_dir: Path) -> None:
    (tum_dir / "accelerometer.txt").write_text("100.0 0 0 9.8\n100.01 0 nan 9.8\n")
    with pytest.raises(DatasetError, match=r"accelerometer.txt:2: column 3 is not finite"):
        TumRgbdSequence(tum_dir)
    (tum_dir / "accelerometer.txt").unlink()
    (tum_dir / "boxes.txt").write_text("100.0 1 5 5 2 6\n")
    with pytest.raises(DatasetError, match=r"boxes.txt:1: box has x2 < x1"):
        TumRgbdSequence(tum_dir)


def test_bad_sensor(tum_dir: Path) -> None:
    with pytest.raises(DatasetError, match="sensor 'stereo' not available"):
        TumRgbdSequence(tum_dir, sensor="stereo")


@pytest.mark.parametrize("which", ["rgb", "depth"])
def test_undecodable_frame_is_skipped_with_warning(tum_dir: Path, which: str, caplog: pytest.LogCaptureFixture) -> None:
    name = (tum_dir / f"{which}.txt").read_text().splitlines()[3].split()[1]  # frame 1
    (tum_dir / name).write_bytes(b"not a png")
    seq = TumRgbdSequence(tum_dir)  # opening does not decode
    assert len(seq) == 5
    with caplog.at_level(logging.WARNING, logger="vslam.data.tum"):
        frames = list(seq)
    assert [f.index for f in frames] == [0, 2, 3, 4]
    assert name in caplog.text and "skipped" in caplog.text
    with pytest.raises(DatasetError, match="does not decode"):
        seq.frame(1)
