"""KITTI odometry reader: calibration, stereo extrinsics, poses, both path forms and every bad-input path."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.data.kitti import KittiSequence, read_kitti_calib
from vslam.errors import DatasetError

H, W = 5, 12
FX, CX, CY, BASE = 700.0, 6.0, 2.5, 0.5


def _P(tx: float, ty: float = 0.0, tz: float = 0.0) -> str:
    """A rectified P = K [I | t] flattened (KITTI stores K @ t in the last column)."""
    K = np.array([[FX, 0, CX], [0, FX, CY], [0, 0, 1]])
    P = np.hstack([K, (K @ np.array([tx, ty, tz]))[:, None]])
    return " ".join(f"{v:.12e}" for v in P.reshape(-1))


def make_kitti(root: Path, seq: str = "03", n: int = 4, cams: tuple[int, ...] = (0, 1), poses: bool = True) -> Path:
    """root/sequences/<seq> with n frames per camera in cams, calib P0..P3 and root/poses/<seq>.txt."""
    sdir = root / "sequences" / seq
    sdir.mkdir(parents=True)
    (sdir / "calib.txt").write_text(
        f"P0: {_P(0)}\nP1: {_P(-BASE)}\nP2: {_P(0.06, -0.001, 0.002)}\nP3: {_P(-0.47, 0.0, 0.003)}\nTr: {' '.join(['0'] * 12)}\n"
    )
    (sdir / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n)))
    for c in cams:
        (sdir / f"image_{c}").mkdir()
        for i in range(n):
            img = np.full((H, W, 3) if c >= 2 else (H, W), 10 * i + c, np.uint8)
            cv2.imwrite(str(sdir / f"image_{c}" / f"{i:06d}.png"), img)
    if poses:
        (root / "poses").mkdir()
        rows = [f"1 0 0 {0.3 * i} 0 1 0 0 0 0 1 {1.0 * i}" for i in range(n)]
        (root / "poses" / f"{seq}.txt").write_text("\n".join(rows) + "\n")
    return sdir


# ------------------------------------------------------------------------------ real data


@pytest.mark.realdata
def test_real_kitti_07(kitti_root: Path, tmp_path: Path) -> None:
    seq = KittiSequence(kitti_root, sequence="07")
    same = KittiSequence(kitti_root / "sequences" / "07")
    assert len(seq) == len(same) == 160 and seq.name == "kitti_07"
    cam = seq.calibration.cam0
    assert (cam.width, cam.height) == (1226, 370)
    assert (cam.fx, cam.cx, cam.cy) == (707.0912, 601.8873, 183.1104)
    t = seq.timestamps()
    assert t[0] == 0.0 and np.all(np.diff(t) > 0)
    gt = seq.groundtruth()
    assert len(gt) == 160 and all(seq.frame_pose(i) is not None for i in range(160))
    np.testing.assert_allclose(gt.poses[0], np.eye(4), atol=1e-9)
    np.testing.assert_array_equal(gt.poses[5], same.groundtruth().poses[5])
    f = seq.frame(0)
    assert f.image.shape == (370, 1226) and f.image.dtype == np.uint8 and f.right is None

    # The subset ships only image_0; borrow it as image_1 to read the real calib in stereo.
    sdir = tmp_path / "sequences" / "07"
    sdir.mkdir(parents=True)
    for name in ("calib.txt", "times.txt"):
        (sdir / name).symlink_to(kitti_root / "sequences" / "07" / name)
    (sdir / "image_0").symlink_to(kitti_root / "sequences" / "07" / "image_0")
    (sdir / "image_1").symlink_to(kitti_root / "sequences" / "07" / "image_0")
    stereo = KittiSequence(sdir, sensor="stereo")
    assert stereo.calibration.baseline == pytest.approx(0.537, abs=0.001)
    assert stereo.calibration.T_body_cam1[0, 3] == pytest.approx(0.537, abs=0.001)
    assert stereo.groundtruth() is None  # no ../../poses beside the borrowed folder


# ------------------------------------------------------------------------------ content


def test_mono_from_root_and_from_sequence_folder(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path, cams=(0,))
    for seq in (KittiSequence(tmp_path, sequence="03"), KittiSequence(tmp_path, sequence=3), KittiSequence(tmp_path), KittiSequence(sdir)):
        assert len(seq) == 4 and seq.sensor == "mono"
        assert seq.frame_pose(2)[0, 3] == pytest.approx(0.6)
    frames = list(KittiSequence(sdir))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert frames[1].image.shape == (H, W) and frames[1].image[0, 0] == 10
    assert frames[1].timestamp == pytest.approx(0.1)


def test_stereo_baseline_and_extrinsics(tmp_path: Path) -> None:
    seq = KittiSequence(make_kitti(tmp_path), sensor="stereo")
    calib = seq.calibration
    assert calib.baseline == pytest.approx(BASE)
    np.testing.assert_allclose(calib.T_body_cam0, np.eye(4))
    np.testing.assert_allclose(calib.T_body_cam1[:3, 3], [BASE, 0, 0], atol=1e-12)  # right camera at +x
    f = seq.frame(2)
    assert f.right.shape == (H, W) and f.right[0, 0] == 21


def test_colour_pair_moves_ground_truth_onto_camera_2(tmp_path: Path) -> None:
    seq = KittiSequence(make_kitti(tmp_path, cams=(2, 3)), sensor="stereo", camera=2)
    f = seq.frame(1)
    assert f.image.shape == (H, W, 3)
    # P2 = K [I | t2] with t2 = (0.06, -0.001, 0.002): camera 2 sits at -t2 in KITTI camera 0.
    T_k0_c2 = np.eye(4)
    T_k0_c2[:3, 3] = [-0.06, 0.001, -0.002]
    T_world_k0 = np.eye(4)
    T_world_k0[:3, 3] = [0.3, 0.0, 1.0]
    np.testing.assert_allclose(f.T_world_cam, T_world_k0 @ T_k0_c2, atol=1e-12)
    np.testing.assert_allclose(seq.calibration.T_body_cam1[:3, 3], [0.53, -0.001, -0.001], atol=1e-12)  # c3 - c2


def test_read_calib_keys(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    P = read_kitti_calib(sdir / "calib.txt")
    assert set(P) == {"P0", "P1", "P2", "P3", "Tr"} and P["P1"][0, 3] == pytest.approx(-FX * BASE)


# ------------------------------------------------------------------------------ bad input


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing KITTI folder"):
        KittiSequence(tmp_path / "nope")


@pytest.mark.parametrize("name", ["calib.txt", "times.txt"])
def test_missing_file(tmp_path: Path, name: str) -> None:
    sdir = make_kitti(tmp_path)
    (sdir / name).unlink()
    with pytest.raises(DatasetError, match=rf"{name}: missing {name}"):
        KittiSequence(sdir)


def test_calib_without_P0(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    text = (sdir / "calib.txt").read_text().splitlines()
    (sdir / "calib.txt").write_text("\n".join(text[1:]) + "\n")
    with pytest.raises(DatasetError, match=r"calib.txt: missing P0"):
        KittiSequence(sdir)


def test_calib_without_right_camera_for_stereo(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    lines = (sdir / "calib.txt").read_text().splitlines()
    (sdir / "calib.txt").write_text("\n".join(ln for ln in lines if not ln.startswith("P1")) + "\n")
    assert len(KittiSequence(sdir)) == 4  # mono needs only P0
    with pytest.raises(DatasetError, match=r"calib.txt: missing P1"):
        KittiSequence(sdir, sensor="stereo")


@pytest.mark.parametrize(
    "text, message",
    [
        ("P1: 1 2 3", r"calib.txt:2: expected 13 columns, found 4"),
        ("P1: 1 2 3 4 5 6 7 8 9 10 11 x", r"calib.txt:2: P1: value 'x' is not a number"),
        ("P1 1 2 3 4 5 6 7 8 9 10 11 12", r"calib.txt:2: expected 'KEY:'"),
        ("P1: 1 2 3 4 5 6 7 8 9 10 11 nan", r"calib.txt:2: P1: holds a value that is not finite"),
    ],
)
def test_bad_calib_line(tmp_path: Path, text: str, message: str) -> None:
    sdir = make_kitti(tmp_path)
    lines = (sdir / "calib.txt").read_text().splitlines()
    lines[1] = text
    (sdir / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=message):
        KittiSequence(sdir)


@pytest.mark.parametrize(
    "times, message",
    [
        ("0\n0.1\n0.1\n0.3\n", r"times.txt:3: timestamp .* repeats"),
        ("0\n0.2\n0.1\n0.3\n", r"times.txt:3: timestamp .* goes back in time"),
        ("0\n0.1\nnan\n0.3\n", r"times.txt:3: column 1 is not finite"),
        ("0\n0.1\n0.2 5\n0.3\n", r"times.txt:3: expected 1 columns, found 2"),
        ("", r"times.txt: lists no times"),
        ("0\n0.1\n0.2\n", r"times.txt: lists 3 times but .*image_0 holds 4 .png images"),
    ],
)
def test_bad_times(tmp_path: Path, times: str, message: str) -> None:
    sdir = make_kitti(tmp_path)
    (sdir / "times.txt").write_text(times)
    with pytest.raises(DatasetError, match=message):
        KittiSequence(sdir)


def test_misnamed_image_names_times_line(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    (sdir / "image_0" / "000002.png").rename(sdir / "image_0" / "frame2.png")
    with pytest.raises(DatasetError, match=r"times.txt:3: frame 2 has no image .*000002.png"):
        KittiSequence(sdir)


def test_stereo_without_right_images(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path, cams=(0,))
    with pytest.raises(DatasetError, match=r"image_1: missing image_1 \(needed for sensor='stereo'\)"):
        KittiSequence(sdir, sensor="stereo")


def test_bad_poses(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    poses = tmp_path / "poses" / "03.txt"
    eye = "1 0 0 0 0 1 0 0 0 0 1 0\n"
    # raised by groundtruth(), not at open: SLAM runs and writes its trajectory before the evaluation fails
    for text, message in ((eye + "1 0 0 0 0 1 0 0 0 0 1\n", r"03.txt:2: expected 12 columns, found 11"),
                          (eye, r"03.txt: has 1 poses for 4 frames"),
                          (eye * 2 + "2 0 0 0 0 1 0 0 0 0 1 0\n" + eye, r"03.txt:3: pose's 3x3 part is not a rotation"),
                          (eye + "1 0 0 0 0 1 0 0 0 0 -1 0\n" + eye * 2, r"03.txt:2: pose's 3x3 part is not a rotation")):
        poses.write_text(text)
        seq = KittiSequence(sdir)
        assert seq.frame_pose(0) is None
        with pytest.raises(DatasetError, match=message):
            seq.groundtruth()


def test_root_with_several_sequences_needs_a_choice(tmp_path: Path) -> None:
    make_kitti(tmp_path, seq="00", poses=False)
    make_kitti(tmp_path, seq="01", poses=False)
    with pytest.raises(DatasetError, match=r"holds sequences \['00', '01'\]; pass sequence="):
        KittiSequence(tmp_path)
    assert KittiSequence(tmp_path, sequence="01").groundtruth() is None
    with pytest.raises(DatasetError, match="missing KITTI sequence 05 folder"):
        KittiSequence(tmp_path, sequence="05")


def test_bad_options(tmp_path: Path) -> None:
    sdir = make_kitti(tmp_path)
    with pytest.raises(DatasetError, match="sensor 'rgbd' not available"):
        KittiSequence(sdir, sensor="rgbd")
    with pytest.raises(DatasetError, match="camera must be 0"):
        KittiSequence(sdir, camera=1)


def test_undecodable_frame_is_skipped_with_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    sdir = make_kitti(tmp_path)
    (sdir / "image_1" / "000001.png").write_bytes(b"garbage")
    (sdir / "image_0" / "000000.png").write_bytes(b"garbage")  # size then comes from the next image
    seq = KittiSequence(sdir, sensor="stereo")
    assert (seq.calibration.cam0.width, seq.calibration.cam0.height) == (W, H)
    with caplog.at_level(logging.WARNING, logger="vslam.data.kitti"):
        frames = list(seq)
    assert [f.index for f in frames] == [2, 3]
    assert "000001.png" in caplog.text and "000000.png" in caplog.text
