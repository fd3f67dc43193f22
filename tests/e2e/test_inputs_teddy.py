"""Your data in, on real frames: an image folder, a lossless video and ROS 1 / ROS 2 bags made from the first
TUM teddy frames give the trajectory the TUM folder of the same frames gives (to 1e-6 m; in fact bit for bit)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.data.make_inputs import TEDDY_CAMERA, write_bag, write_video
from vslam.data.trajectory import Trajectory
from vslam.paths import data_root
from vslam.pipeline import Pipeline, PipelineConfig

pytestmark = pytest.mark.realdata

N = 30  # frames: a monocular map initialises within them
MAX_DIFF = 0.02  # s, the TUM rgb<->depth association bound (DatasetConfig.max_diff)


def _times(path: Path) -> list[tuple[float, str]]:
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return [(float(t), f) for t, f in rows]


@pytest.fixture(scope="module")
def teddy_subset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A TUM folder of the first N teddy rgb images and the depth images up to max_diff after the last one."""
    src = data_root() / "tum" / "rgbd_dataset_freiburg3_teddy"
    if not src.is_dir():
        pytest.skip(f"real data not found at {src} (set VSLAM_DATA to the folder holding tum/)")
    root = tmp_path_factory.mktemp("tum") / src.name  # the folder name picks the freiburg3 camera
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb = _times(src / "rgb.txt")[:N]
    depth = [(t, f) for t, f in _times(src / "depth.txt") if t <= rgb[-1][0] + MAX_DIFF]
    for name, rows in (("rgb", rgb), ("depth", depth)):
        for _, f in rows:
            (root / f).symlink_to(src / f)
        # the timestamps exactly as TUM writes them (file name stems)
        (root / f"{name}.txt").write_text("".join(f"{Path(f).stem} {f}\n" for _, f in rows))
    return root


def _run(out: Path, **dataset: object) -> Trajectory:
    cfg = PipelineConfig.load(None, {"dataset": dataset, "output": {"dir": str(out), "report": False},
                                     "eval": {"enabled": False}})
    res = Pipeline(cfg).run()
    assert res.error is None and res.tracked.sum() >= N // 2, "too few frames tracked to compare trajectories"
    return res.trajectory


@pytest.fixture(scope="module")
def reference(teddy_subset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Trajectory]:
    """The TUM-folder trajectories, RGB-D and monocular, computed once for every comparison."""
    out = tmp_path_factory.mktemp("ref")
    return {s: _run(out / s, kind="tum", path=str(teddy_subset), sensor=s) for s in ("rgbd", "mono")}


def _assert_same(est: Trajectory, ref: Trajectory, times: bool = True) -> None:
    assert len(est) == len(ref) == N
    assert np.linalg.norm(ref.poses[-1, :3, 3] - ref.poses[0, :3, 3]) > 1e-3  # the camera moved: a real check
    assert np.abs(est.poses[:, :3, 3] - ref.poses[:, :3, 3]).max() <= 1e-6  # metres
    assert np.abs(est.poses[:, :3, :3] - ref.poses[:, :3, :3]).max() <= 1e-9
    if times:
        np.testing.assert_allclose(est.timestamps, ref.timestamps, rtol=0, atol=1e-6)


def test_image_folder_with_depth_equals_the_tum_folder(teddy_subset: Path, reference: dict[str, Trajectory],
                                                       tmp_path: Path) -> None:
    root = tmp_path / "mine"
    for sub in ("rgb", "depth"):
        (root / sub).mkdir(parents=True)
        for f in (teddy_subset / sub).iterdir():
            (root / sub / f.name).symlink_to(f.resolve())
    # times from the file names (TUM's 1305031102.175304.png), depth matched by time
    (root / "camera.yaml").write_text(TEDDY_CAMERA + "images: rgb\ndepth: depth\ndepth_scale: 5000\n")
    _assert_same(_run(tmp_path / "out", kind="auto", path=str(root), sensor="rgbd"), reference["rgbd"])


def test_lossless_video_equals_the_tum_folder(teddy_subset: Path, reference: dict[str, Trajectory],
                                              tmp_path: Path) -> None:
    rgb = [teddy_subset / f for _, f in _times(teddy_subset / "rgb.txt")]
    images = [cv2.imread(str(f)) for f in rgb]
    video = write_video(tmp_path / "teddy.avi", images)
    cap = cv2.VideoCapture(str(video))
    back = [cap.read()[1] for _ in images]
    assert all(b is not None and np.array_equal(a, b) for a, b in zip(images, back)), "FFV1 round trip not lossless"
    (tmp_path / "camera.yaml").write_text(TEDDY_CAMERA)
    est = _run(tmp_path / "out", kind="auto", path=str(video), sensor="mono")
    _assert_same(est, reference["mono"], times=False)
    np.testing.assert_allclose(est.timestamps, np.arange(N) / 30.0, atol=1e-6)  # the container's times


@pytest.mark.parametrize("ros", [1, 2])
def test_ros_bag_equals_the_tum_folder(ros: int, teddy_subset: Path, reference: dict[str, Trajectory],
                                       tmp_path: Path) -> None:
    pytest.importorskip("rosbags", reason="the optional 'bags' extra (rosbags) is not installed")
    rgb = [(t, teddy_subset / f) for t, f in _times(teddy_subset / "rgb.txt")]
    depth = [(t, teddy_subset / f) for t, f in _times(teddy_subset / "depth.txt")]
    if ros == 1:  # as TUM publishes them: depth in metres (32FC1), intrinsics from camera_info
        bag = write_bag(tmp_path / "teddy.bag", 1, rgb, depth, depth_encoding="32FC1")
    else:  # raw 16-bit depth, intrinsics and depth scale from camera.yaml beside the bag
        bag = write_bag(tmp_path / "teddy", 2, rgb, depth, depth_encoding="16UC1", camera_info=False)
        (bag / "camera.yaml").write_text(TEDDY_CAMERA + "depth_scale: 5000\n")
    _assert_same(_run(tmp_path / "out", kind="auto", path=str(bag), sensor="rgbd"), reference["rgbd"])
