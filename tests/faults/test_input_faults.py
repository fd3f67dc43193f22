"""Issue 56, items 1 and 4, through the command line on small copies of the real subsets: a calibration no camera
can have is one line naming the file, the field and the range expected (exit 2), whichever reader read it (camera
file, ORB-SLAM3 settings, KITTI calib.txt, EuRoC sensor.yaml, the TUM defaults); an image of another size than
the calibration's is named; a frame that does not decode (a damaged video frame, a corrupt PNG) is a warning naming
it and the run goes on past it; nothing decoding at all is an error."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.faults.conftest import _data_lines, _need
from tests.faults.test_run_faults import FAST, one_error_line

TEDDY_CAMERA = "fx: 535.4\nfy: 539.2\ncx: 320.1\ncy: 247.6\n"  # TUM freiburg3; lines 1-4


def _teddy_rgb(n: int) -> list[Path]:
    src = _need("tum/rgbd_dataset_freiburg3_teddy")
    return [src / row.split()[1] for row in _data_lines(src / "rgb.txt")[1][:n]]


def _image_folder(root: Path, n: int = 40, camera: str = TEDDY_CAMERA) -> Path:
    """``root`` holding the first ``n`` teddy rgb images (symlinks, named by their TUM times) and camera.yaml."""
    root.mkdir(parents=True)
    for f in _teddy_rgb(n):
        os.symlink(f, root / f.name)
    (root / "camera.yaml").write_text(camera)
    return root


def _copy_euroc(dst: Path) -> Path:
    """V1_01 micro with its lists and sensor.yaml files copied (so a case can break them), the rest linked."""
    src = _need("euroc/V1_01_easy_micro") / "mav0"
    mav0 = dst / "V1_01_easy" / "mav0"
    for cam in ("cam0", "cam1"):
        (mav0 / cam).mkdir(parents=True)
        os.symlink(src / cam / "data", mav0 / cam / "data")
        for name in ("data.csv", "sensor.yaml"):
            shutil.copy(src / cam / name, mav0 / cam / name)
    for sub in ("imu0", "state_groundtruth_estimate0"):
        if (src / sub).is_dir():
            os.symlink(src / sub, mav0 / sub)
    return mav0.parent


def _line_of(path: Path, key: str) -> int:
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if ln.startswith(key))


def _warnings(caplog: pytest.LogCaptureFixture, needle: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and needle in r.getMessage()]


def _stats_indices(out: Path) -> list[int]:
    rows = (out / "stats.csv").read_text().splitlines()
    col = rows[0].split(",").index("index")
    return [int(r.split(",")[col]) for r in rows[1:]]


# -- item 1: calibration out of range, every reader ----------------------------------------------------------------


@pytest.mark.parametrize("camera, needle", [
    (TEDDY_CAMERA.replace("cx: 320.1", "cx: 5000"),
     "camera.yaml:3: cx = 5000: the principal point must lie inside the image: 0..640 (the image width, 640x480)"),
    (TEDDY_CAMERA.replace("cy: 247.6", "cy: -5"),
     "camera.yaml:4: cy = -5: the principal point must lie inside the image (>= 0 pixels)"),
    (TEDDY_CAMERA.replace("fx: 535.4", "fx: 0"), "camera.yaml:1: 'fx' must be a positive number, got 0"),
    (TEDDY_CAMERA.replace("fy: 539.2", "fy: -539.2"), "camera.yaml:2: 'fy' must be a positive number, got -539.2"),
    (TEDDY_CAMERA.replace("fx: 535.4", "fx: 5354"),
     "camera.yaml:2: fx / fy = 5354 / 539.2 = 9.93: the focal lengths' ratio must be within 0.2..5"),
    (TEDDY_CAMERA + "distortion_model: radtan\ndistortion: [250.0, 0.1, 0.0, 0.0]\n",
     "camera.yaml:6: distortion k1 = 250: radial distortion coefficients of a real lens lie within -10..10 (radtan"),
    (TEDDY_CAMERA + "distortion_model: radtan\ndistortion: [0.1, 0.1, 3.0, 0.0]\n",
     "camera.yaml:6: distortion p1 = 3: tangential distortion coefficients of a real lens lie within -1..1"),
    (TEDDY_CAMERA + "distortion_model: equidistant\ndistortion: [0.01, .nan, 0.0, 0.0]\n",
     "camera.yaml:6: 'distortion' must be a list of finite numbers"),
])
def test_camera_file_out_of_range_is_one_line(cli, tmp_path, camera, needle):
    folder = _image_folder(tmp_path / "mine", n=3, camera=camera)
    rc, _, err = cli("run", "--data", folder, "--sensor", "mono", "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, needle)
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_orbslam3_settings_out_of_range_name_their_key(cli, tmp_path):
    folder = _image_folder(tmp_path / "mine", n=3, camera="")
    settings = tmp_path / "orb.yaml"
    settings.write_text('%YAML:1.0\nCamera.type: "PinHole"\nCamera1.fx: 535.4\nCamera1.fy: 539.2\n'
                        "Camera1.cx: 320.1\nCamera1.cy: 2000.0\nCamera.width: 640\nCamera.height: 480\n")
    rc, _, err = cli("run", "--data", folder, "--camera", settings, "--sensor", "mono", "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "orb.yaml:6: Camera1.cy = 2000: the principal point must lie inside the image: 0..480")


@pytest.mark.parametrize("fx, shown", [("0.000000000000e+00", "0"), ("-7.070912000000e+02", "-707.091")])
def test_kitti_focal_length_not_positive(cli, kitti40, tmp_path, fx, shown):
    calib = kitti40 / "calib.txt"
    calib.write_text(calib.read_text().replace("P0: 7.070912000000e+02", f"P0: {fx}", 1))
    rc, _, err = cli("run", "--preset", "kitti_mono", "--data", kitti40, "-o", tmp_path / "out", *FAST)
    # was: "internal error: LinAlgError" (fx = 0) or a generic "no frame tracked" (fx < 0)
    one_error_line(rc, err, f"calib.txt:1: P0 fx (P0[0,0]) = {shown}: focal lengths must be finite and > 0 pixels")


def test_kitti_principal_point_outside_the_image(cli, kitti40, tmp_path):
    calib = kitti40 / "calib.txt"
    calib.write_text(calib.read_text().replace("6.018873000000e+02", "6.018873000000e+03", 1))
    rc, _, err = cli("run", "--preset", "kitti_mono", "--data", kitti40, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "calib.txt:1: P0 cx (P0[0,2]) = 6018.87: the principal point must lie inside the image: "
                            "0..1226")


def test_kitti_projection_that_is_not_rectified(cli, kitti40, tmp_path):
    calib = kitti40 / "calib.txt"
    calib.write_text(calib.read_text().replace("P0: 7.070912000000e+02 0.000000000000e+00", "P0: 7.070912000000e+02 2.5",
                                               1))
    rc, _, err = cli("run", "--preset", "kitti_mono", "--data", kitti40, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "calib.txt:1: P0 is not a rectified projection K [I | t]: its first three columns must be "
                            "[[fx 0 cx] [0 fy cy] [0 0 1]], found [707.091 2.5 601.887 0 707.091 183.11 0 0 1]")


def test_bag_camera_info_out_of_range_names_the_topic(tmp_path):
    from types import SimpleNamespace

    from vslam.data.bag import camera_from_info
    from vslam.errors import DatasetError

    def info(k, d=(0.0,) * 5):
        return SimpleNamespace(k=k, d=list(d), distortion_model="plumb_bob", width=640, height=480)

    bag, topic = tmp_path / "b.bag", "/camera/rgb/camera_info"
    with pytest.raises(DatasetError, match=r"b.bag: /camera/rgb/camera_info: camera_info cx \(K\[2\]\) = 3200.1: the "
                                           r"principal point must lie inside the image: 0..640"):
        camera_from_info(info([535.4, 0, 3200.1, 0, 539.2, 247.6, 0, 0, 1]), bag, topic)
    with pytest.raises(DatasetError, match=r"camera_info D k1 = -40: radial distortion coefficients of a real lens"):
        camera_from_info(info([535.4, 0, 320.1, 0, 539.2, 247.6, 0, 0, 1], (-40.0, 0.1, 0.0, 0.0, 0.0)), bag, topic)


@pytest.mark.parametrize("old, new, needle", [
    ("intrinsics: [458.654,", "intrinsics: [0.0,", "intrinsics fu = 0: focal lengths must be finite and > 0 pixels"),
    ("intrinsics: [458.654, 457.296, 367.215,", "intrinsics: [458.654, 457.296, 3672.15,",
     "intrinsics cu = 3672.15: the principal point must lie inside the image: 0..752"),
    ("distortion_coefficients: [-0.28340811,", "distortion_coefficients: [-28.340811,",
     "distortion_coefficients k1 = -28.3408: radial distortion coefficients of a real lens lie within -10..10"),
    ("resolution: [752, 480]", "resolution: [640, 480]",
     "image is 752x480, but {yaml} (resolution) says 640x480: the calibration is of another image size"),
])
def test_euroc_sensor_yaml_out_of_range(cli, tmp_path, old, new, needle):
    seq = _copy_euroc(tmp_path / "data")
    yaml = seq / "mav0" / "cam0" / "sensor.yaml"
    key = new.split(":")[0]
    assert old in yaml.read_text()
    yaml.write_text(yaml.read_text().replace(old, new, 1))
    rc, _, err = cli("run", "--preset", "euroc_stereo", "--data", seq, "-o", tmp_path / "out", *FAST)
    if "image is" in needle:  # named: the first image, and the file that says otherwise
        first = _data_lines(seq / "mav0" / "cam0" / "data.csv")[1][0].split(",")[1]
        one_error_line(rc, err, f"cam0/data/{first}: " + needle.format(yaml=yaml))
    else:
        one_error_line(rc, err, f"cam0/sensor.yaml:{_line_of(yaml, key)}: {needle}")


def test_euroc_stereo_pair_without_a_baseline(cli, tmp_path):
    seq = _copy_euroc(tmp_path / "data")
    shutil.copy(seq / "mav0" / "cam0" / "sensor.yaml", seq / "mav0" / "cam1" / "sensor.yaml")  # cam1 where cam0 is
    rc, _, err = cli("run", "--preset", "euroc_stereo", "--data", seq, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "cam1/sensor.yaml:7: T_BS (the baseline from cam0/sensor.yaml's T_BS): stereo baseline "
                            "= 0 m: the two cameras' centres must be apart")


# -- item 1: an image of another size than the calibration's --------------------------------------------------------


def test_image_folder_of_another_size_than_the_camera_file_names_the_image(cli, tmp_path):
    folder = _image_folder(tmp_path / "mine", n=3, camera=TEDDY_CAMERA + "width: 1280\nheight: 960\n")
    first = sorted(folder.glob("*.png"))[0]
    rc, _, err = cli("run", "--data", folder, "--sensor", "mono", "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, f"{first}: camera is 1280x960 but the images are 640x480; fix width/height in "
                            f"{folder / 'camera.yaml'}")


def test_tum_first_image_of_another_size_is_an_error(cli, tum40, tmp_path):
    rel = _data_lines(tum40 / "rgb.txt")[1][0].split()[1]
    (tum40 / rel).unlink()
    cv2.imwrite(str(tum40 / rel), np.zeros((240, 320, 3), np.uint8))
    rc, _, err = cli("run", "--preset", "tum_rgbd", "--data", tum40, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, f"{tum40 / rel}: image is 320x240, but the TUM freiburg3 camera (named by the folder; "
                            "give calibration.yaml otherwise) says 640x480")


# -- item 4: frames that do not decode ------------------------------------------------------------------------------


def _video(path: Path, n: int, damaged: int | None) -> Path:
    """A lossless FFV1 .avi of the first ``n`` teddy frames; frame ``damaged``'s last 64 bytes overwritten (its
    slice table: FFmpeg then refuses that frame alone)."""
    from tests.data.make_inputs import write_video

    write_video(path, [cv2.imread(str(f)) for f in _teddy_rgb(n)])
    if damaged is not None:
        data = bytearray(path.read_bytes())
        chunks = [m.start() for m in re.finditer(rb"00dc", data)][1:]  # the first is the stream header's
        at = chunks[damaged]
        end = at + 8 + int.from_bytes(data[at + 4:at + 8], "little")
        data[end - 64:end] = b"\xff" * 64
        path.write_bytes(bytes(data))
    return path


def test_video_frame_that_does_not_decode_is_named_and_the_run_goes_on(cli, tmp_path, caplog):
    video = _video(tmp_path / "walk.avi", 40, damaged=20)
    (tmp_path / "camera.yaml").write_text(TEDDY_CAMERA)
    out = tmp_path / "out"
    rc, stdout, err = cli("run", "--data", video, "--sensor", "mono", "-o", out, *FAST)
    assert rc == 0 and "Traceback" not in err, err
    # was: reading stopped at the damaged frame, 20 frames processed, exit 0, no warning
    assert _warnings(caplog, "does not decode") == [f"{video}: frame 20 (1 of 40) does not decode; skipped"]
    assert _stats_indices(out) == [i for i in range(40) if i != 20]
    assert "frames: 39 read, " in stdout and "1 skipped (did not decode: frame 20)" in stdout


def test_video_that_stops_decoding_says_how_many_frames_were_read(tmp_path, caplog):
    from vslam.data.video import MAX_FAILED_READS, VideoSequence

    video = _video(tmp_path / "walk.avi", 12, damaged=None)
    data = bytearray(video.read_bytes())
    chunks = [m.start() for m in re.finditer(rb"00dc", data)][1:]
    for at in chunks[8:12]:  # the last four frames: every read from frame 8 on fails
        end = at + 8 + int.from_bytes(data[at + 4:at + 8], "little")
        data[end - 64:end] = b"\xff" * 64
    video.write_bytes(bytes(data))
    (tmp_path / "camera.yaml").write_text(TEDDY_CAMERA)
    seq = VideoSequence(video)
    assert [f.index for f in seq] == list(range(8))
    assert _warnings(caplog, "container declares") == [
        f"{video}: the container declares 12 frames but 8 were read ({MAX_FAILED_READS} reads in a row failed after "
        "frame 7); the 4 missing are skipped"]
    assert [i for i, _ in seq.skipped] == [8, 9, 10, 11]


def test_corrupt_png_in_an_image_folder_is_named_and_the_run_goes_on(cli, tmp_path, caplog):
    folder = _image_folder(tmp_path / "mine", n=40)
    bad = sorted(folder.glob("*.png"))[12]
    bad.unlink()
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))  # a PNG signature, then nothing a decoder can use
    out = tmp_path / "out"
    rc, stdout, err = cli("run", "--data", folder, "--sensor", "mono", "-o", out, *FAST)
    assert rc == 0 and "Traceback" not in err, err
    assert _warnings(caplog, "does not decode") == [f"{bad}: image does not decode; frame 12 skipped"]
    assert "frames: 39 read, " in stdout and "1 skipped (did not decode: frame 12)" in stdout
    assert _stats_indices(out) == [i for i in range(40) if i != 12]


def test_image_folder_where_no_image_decodes_is_an_error(cli, tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    for k in range(3):
        (folder / f"{k:06d}.png").write_bytes(b"not a png")
    (folder / "camera.yaml").write_text(TEDDY_CAMERA)
    rc, _, err = cli("run", "--data", folder, "--sensor", "mono", "--fps", 30, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, f"{folder}: none of the 3 images decodes (first: 000000.png)")
