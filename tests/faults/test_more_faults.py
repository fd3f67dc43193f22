"""Issue 56, the last three cases, on 40-frame copies of the real subsets: depth in a wrong unit is a warning
naming the median depth when the data opens (TUM, image folder, bag); a bad ``--set`` value names the --set, not
the preset it was merged into (a mistake in a config file keeps naming the file and the line); weights of another
shape than the network are one line naming the file, the first parameter that does not fit and both shapes."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tests.faults.conftest import _data_lines
from tests.faults.test_input_faults import TEDDY_CAMERA, _warnings
from tests.faults.test_run_faults import FAST, TUM, one_error_line
from vslam.data.tum import TumRgbdSequence

# the first teddy depth image's median, 2.143 m (1341841873.273820.png, 74 % of its pixels valid)
TEDDY_FIRST_MEDIAN = 2.143


# -- depth in a wrong unit -------------------------------------------------------------------------------------


def _depth_files(root: Path) -> list[Path]:
    return [root / row.split()[1] for row in _data_lines(root / "depth.txt")[1]]


def test_real_tum_depth_passes_and_its_median_is_kept(tum40, caplog):
    with caplog.at_level(logging.WARNING):
        seq = TumRgbdSequence(tum40)
    assert seq.depth_median_m == pytest.approx(TEDDY_FIRST_MEDIAN, abs=1e-3)
    assert not _warnings(caplog, "depth")


def test_depth_pngs_in_tenths_of_the_unit_are_warned_in_a_run(cli, tum40, tmp_path, caplog):
    for f in _depth_files(tum40):  # written in units of 1/500 m, read as TUM's 1/5000 m
        raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        f.unlink()
        cv2.imwrite(str(f), (raw // 10).astype(np.uint16))
    with caplog.at_level(logging.WARNING):
        rc, _, err = cli("run", "-c", TUM, "--data", tum40, "--max-frames", 3, "--no-eval", "-o", tmp_path / "out", *FAST)
    assert rc == 0, err  # a warning, not an error
    (line,) = _warnings(caplog, "median depth")
    first = _depth_files(tum40)[0]
    assert line == (f"{first}: median depth 0.214 m after depth scale 1/5000 (expected 0.25-10 m for an RGB-D camera): "
                    "is the depth unit right (TUM's 5000 units per metre; depth_scale in calibration.yaml otherwise)?")


def test_depth_scale_off_by_1000_is_warned(tum40, caplog):
    (tum40 / "calibration.yaml").write_text("depth_scale: 5\n")
    with caplog.at_level(logging.WARNING):
        seq = TumRgbdSequence(tum40)
    assert seq.depth_median_m == pytest.approx(1000 * TEDDY_FIRST_MEDIAN, rel=1e-3)
    (line,) = _warnings(caplog, "median depth")
    assert "median depth 2143 m after depth scale 1/5" in line and f"depth_scale in {tum40 / 'calibration.yaml'}" in line


def test_image_folder_depth_scale_is_checked(tum40, caplog):
    from vslam.data.images import ImageFolderSequence

    cam = tum40 / "camera.yaml"
    cam.write_text(TEDDY_CAMERA + "images: rgb\ndepth: depth\ndepth_scale: 5000000\n")  # micrometres
    with caplog.at_level(logging.WARNING):
        seq = ImageFolderSequence(tum40 / "rgb", camera=cam, sensor="rgbd")
    assert seq.depth_median_m == pytest.approx(TEDDY_FIRST_MEDIAN / 1000, rel=1e-3)
    (line,) = _warnings(caplog, "median depth")
    assert "median depth 0.00214 m after depth scale 1/5e+06" in line and f"depth_scale in {cam}" in line
    caplog.clear()
    cam.write_text(TEDDY_CAMERA + "images: rgb\ndepth: depth\ndepth_scale: 5000\n")
    with caplog.at_level(logging.WARNING):
        ImageFolderSequence(tum40 / "rgb", camera=cam, sensor="rgbd")
    assert not _warnings(caplog, "median depth")


def test_bag_with_tum_depth_read_as_millimetres_is_warned(tum40, tmp_path, caplog):
    pytest.importorskip("rosbags", reason="the optional 'bags' extra (rosbags) is not installed")
    from tests.data.make_inputs import write_bag
    from vslam.data.bag import BagSequence

    rgb = [(float(r.split()[0]), tum40 / r.split()[1]) for r in _data_lines(tum40 / "rgb.txt")[1][:4]]
    depth = [(float(r.split()[0]), tum40 / r.split()[1]) for r in _data_lines(tum40 / "depth.txt")[1][:4]]
    bag = write_bag(tmp_path / "b.bag", 1, rgb, depth, depth_encoding="16UC1")  # TUM's 1/5000 m, no camera file
    with caplog.at_level(logging.WARNING):
        seq = BagSequence(bag, sensor="rgbd")
    assert seq.depth_median_m == pytest.approx(5 * TEDDY_FIRST_MEDIAN, rel=1e-3)
    (line,) = _warnings(caplog, "median depth")
    assert line.startswith(f"{bag}:/camera/depth/image: median depth 10.7 m after depth scale 1/1000 ") and "REP 118" in line
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # the same bag as published: 32FC1 metres
        BagSequence(write_bag(tmp_path / "m.bag", 1, rgb, depth, depth_encoding="32FC1"), sensor="rgbd")
    assert not _warnings(caplog, "median depth")


def test_depth_with_almost_no_valid_pixel_is_warned(tum40, caplog):
    for f in _depth_files(tum40)[:3]:
        raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        raw[40:] = 0  # 8 % of the rows left
        f.unlink()
        cv2.imwrite(str(f), raw)
    with caplog.at_level(logging.WARNING):
        TumRgbdSequence(tum40)
    (line,) = _warnings(caplog, "pixels are valid")
    assert re.search(r"only \d\.\d % of the first depth image's pixels are valid \(expected at least 10 %", line)


# -- a bad --set value names the --set -------------------------------------------------------------------------


@pytest.mark.parametrize("item, needle", [
    ("slam.features.n_features=abc", "'slam.features.n_features' must be an integer, got 'abc'"),
    ("slam.features.n_features=-5", "'slam.features.n_features' must be a finite number >= 0, got -5"),
    ("slam.features.n_features=0", "n_features must be at least 1, got 0"),
    ("slam.features.n_featurs=5", "unknown key 'slam.features.n_featurs'"),
    ("dataset.drop=[[1,x]]", "'dataset.drop[0][1]' must be an integer, got 'x'"),
])
def test_bad_set_value_names_the_set_not_the_preset(cli, tum40, tmp_path, item, needle):
    rc, _, err = cli("run", "--preset", "tum_rgbd", "--data", tum40, "-o", tmp_path / "out", "--set", item)
    line = one_error_line(rc, err, needle)
    assert line.startswith(f"vslam: error: --set {item}: "), line
    assert "tum_rgbd.yaml" not in line
    assert not (tmp_path / "out").exists()


def test_bad_value_in_a_config_file_names_the_file_and_line(cli, tum40, tmp_path):
    cfg = tmp_path / "my.yaml"
    cfg.write_text("dataset:\n  kind: tum\nslam:\n  features:\n    n_features: abc\n")
    rc, _, err = cli("run", "-c", cfg, "--data", tum40, "-o", tmp_path / "out")
    one_error_line(rc, err, f"{cfg}:5: 'slam.features.n_features' must be an integer, got 'abc'")
    # the same key set right by --set: the file's mistake is gone, and a --set mistake elsewhere names the --set
    rc, _, err = cli("run", "-c", cfg, "--data", tum40, "-o", tmp_path / "out", "--set", "slam.features.n_features=900",
                     "--set", "slam.features.n_levels=-1")
    one_error_line(rc, err, "--set slam.features.n_levels=-1: 'slam.features.n_levels' must be a finite number >= 0")


# -- weights of another shape than the network -----------------------------------------------------------------


def test_detector_checkpoint_of_another_shape_is_one_line(cli, tum40, tmp_path):
    from vslam.dynamic.detector import default_weights

    ck = torch.load(default_weights(), weights_only=True)
    ck["config"]["num_classes"], ck["names"] = 80, [f"class{i}" for i in range(80)]  # tensors of 2 classes
    bad = tmp_path / "det80.pt"
    torch.save(ck, bad)
    rc, _, err = cli("run", "-c", TUM, "--data", tum40, "--max-frames", 3, "-o", tmp_path / "out", *FAST,
                     "--set", "slam.dynamic.enabled=true", "--set", "slam.dynamic.source=detector",
                     "--set", f"slam.dynamic.weights={bad}")
    line = one_error_line(rc, err, f"{bad}: detector checkpoint does not fit the network: 'head.cls.0.0.conv.weight' "
                                   "is (64, 64, 3, 3) in the file, the network expects (80, 64, 3, 3)",
                          "its tensors are a detector of 2 classes", "its config says 80 classes")
    assert "Error(s) in loading state_dict" not in line


def test_keypoint_checkpoint_of_another_shape_is_one_line(cli, tum40, tmp_path):
    from vslam.features.convpoint import default_weights

    ck = torch.load(default_weights(), weights_only=True)
    ck["config"]["desc_dim"] = 256  # tensors of 128
    bad = tmp_path / "cp256.pt"
    torch.save(ck, bad)
    rc, _, err = cli("run", "-c", TUM, "--data", tum40, "--max-frames", 3, "-o", tmp_path / "out", *FAST,
                     "--set", "slam.features.extractor=convpoint", "--set", f"slam.features.weights={bad}")
    one_error_line(rc, err, f"{bad}: ConvPoint checkpoint does not fit the network: 'desc.3.weight' is "
                            "(128, 128, 1, 1) in the file, the network expects (256, 128, 1, 1)", "desc_dim 128")


def test_resume_state_of_another_shape_is_one_line(cli, tmp_path):
    """A keypoint trainer's ``last.pt`` whose descriptor head has another size than the --toy network's."""
    from tests.nn.test_checkpoint import TINY_POINT, _keypoint_last

    out = tmp_path / "run"
    out.mkdir()
    last = _keypoint_last(out / "last.pt")
    ck = torch.load(last, weights_only=True)
    d = TINY_POINT["desc_dim"]
    ck["model"]["desc.3.weight"] = torch.zeros(2 * d, d, 1, 1)
    torch.save(ck, last)
    rc, _, err = cli("train", "keypoints", "--toy", "--resume", "-o", out, "--set", "threads=1")
    line = one_error_line(rc, err, f"{last}: keypoint training checkpoint does not fit the network: 'desc.3.weight' is "
                                   f"({2 * d}, {d}, 1, 1) in the file, the network expects ({d}, {d}, 1, 1)")
    assert line.endswith("; resume refused")
