"""Issue 56, item 2, on 40-frame copies of the real subsets: RGB-depth and left-right pairing is checked, not
assumed. Depth no frame can use (8-bit, another size) is refused when the data opens (exit 2, the file named);
a depth list that pairs with nothing is an error naming the distance to the nearest image; one whose times are
shifted, or that leaves more than 5 % of the frames without a partner, is a warning naming the shift or the
files; ``sequence.association`` counts the frames listed, paired and dropped (and why)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.faults.conftest import N, _data_lines, _need
from tests.faults.test_input_faults import _copy_euroc, _warnings
from tests.faults.test_run_faults import FAST, TUM, one_error_line
from vslam.data.association import DROP_WARN_FRACTION
from vslam.data.euroc import EurocSequence
from vslam.data.tum import TumRgbdSequence


def _depth_files(root: Path) -> list[Path]:
    return [root / row.split()[1] for row in _data_lines(root / "depth.txt")[1]]


def _rewrite_depth(root: Path, convert) -> None:
    """Replace every depth image of the copy (symlinks into the real data) by ``convert(raw uint16)``."""
    for f in _depth_files(root):
        raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        f.unlink()
        cv2.imwrite(str(f), convert(raw))


def _edit_depth_list(root: Path, edit) -> None:
    head, rows = _data_lines(root / "depth.txt")
    (root / "depth.txt").write_text("\n".join(head + edit(rows)) + "\n")


# -- depth no frame can use: refused when the data opens, not skipped frame by frame (every frame was, and the
#    run ended "frames: 0", exit 0) ----------------------------------------------------------------------------


@pytest.mark.parametrize("convert, needle", [
    (lambda d: (d // 256).astype(np.uint8), "depth image is 8-bit (uint8), expected 16-bit single-channel depth"),
    (lambda d: cv2.cvtColor((d // 256).astype(np.uint8), cv2.COLOR_GRAY2BGR), "depth image is 8-bit (uint8, 3 channels)"),
    (lambda d: cv2.resize(d, (320, 240), interpolation=cv2.INTER_NEAREST),
     "depth image is 320x240, the rgb images are 640x480"),
])
def test_depth_that_no_frame_can_use_is_refused_at_open(cli, tum40, tmp_path, convert, needle):
    _rewrite_depth(tum40, convert)
    out = tmp_path / "out"
    rc, _, err = cli("run", "-c", TUM, "--data", tum40, "-o", out, *FAST)
    line = one_error_line(rc, err, needle, "--sensor mono")
    assert str(_depth_files(tum40)[0]) in line  # the file is named
    assert not (out / "trajectory.tum.txt").exists()  # refused before a frame was read


# -- depth.txt shifted by 0.5 s: at 30 Hz the shifted times still land within 4 ms of other rgb images, so 25 of
#    40 pair (each with the depth of 0.5 s earlier) and 15 have none: a warning naming the shift, not an error --


def test_depth_list_shifted_by_half_a_second_is_named(cli, tum40, tmp_path, caplog):
    _edit_depth_list(tum40, lambda rows: [f"{float(r.split()[0]) + 0.5:.6f} {r.split()[1]}" for r in rows])
    seq = TumRgbdSequence(tum40)
    a = seq.association
    assert (a.kind, a.inputs, a.paired, len(a.dropped), a.partners) == ("rgb-depth", N, 25, 15, N)
    assert a.shift_s == pytest.approx(0.5, abs=0.005) and a.unpaired_kept and len(seq) == N
    assert a.dropped[0] == ("rgb/1341841873.273798.png", "no depth image within 0.02 s (nearest 0.500 s away)")
    assert "depth times look shifted by +0.500 s" in a.summary()
    caplog.clear()
    rc, _, err = cli("run", "-c", TUM, "--data", tum40, "--max-frames", 18, "-o", tmp_path / "out", *FAST)
    assert rc == 0, err  # the times alone cannot prove a shift (a depth stream may start and stop late): warned
    (shift,) = _warnings(caplog, "look shifted")
    assert shift.startswith(f"{tum40 / 'depth.txt'}: the depth times look shifted by +0.500 s against the rgb times")
    assert "40 of 40 rgb images would pair instead of 25" in shift
    (drop,) = _warnings(caplog, "have no depth image")
    assert "15 of 40 rgb images (38 %) have no depth image within 0.02 s" in drop
    assert "rgb/1341841873.273798.png, rgb/1341841873.305888.png, rgb/1341841873.341935.png and 12 more" in drop


def test_depth_list_shifted_past_every_rgb_image_is_an_error(cli, tum40, tmp_path):
    _edit_depth_list(tum40, lambda rows: [f"{float(r.split()[0]) + 10:.6f} {r.split()[1]}" for r in rows])
    rc, _, err = cli("run", "-c", TUM, "--data", tum40, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "depth.txt: no rgb image has a depth image within 0.02 s (40 rgb images",
                   "the nearest are 8.692 s apart; depth.txt starts 10.000 s after the rgb images: are depth.txt's "
                   "times shifted?)", "--sensor mono")


def test_depth_clock_offset_within_the_tolerance_is_named(tum40, caplog):
    """Every rgb image gets a depth image, but all 13 ms later (streams in lockstep, one clock off)."""
    rgb = [float(r.split()[0]) for r in _data_lines(tum40 / "rgb.txt")[1]]
    _edit_depth_list(tum40, lambda rows: [f"{t + 0.013:.6f} {r.split()[1]}" for t, r in zip(rgb, rows)])
    a = TumRgbdSequence(tum40).association
    assert (a.paired, a.dropped) == (N, []) and a.shift_s == pytest.approx(0.013, abs=1e-4)
    (w,) = _warnings(caplog, "median offset")
    assert "depth images are paired at a median offset of +0.013 s (tolerance 0.02 s)" in w


# -- a few depth images missing: counted; warned only above the threshold --------------------------------------


@pytest.mark.parametrize("removed", [2, 3])
def test_a_few_missing_depth_images_are_counted(tum40, caplog, removed):
    gone = [10, 20, 30][:removed]
    names = [r.split()[1] for r in _data_lines(tum40 / "rgb.txt")[1]]
    _edit_depth_list(tum40, lambda rows: [r for k, r in enumerate(rows) if k not in gone])
    seq = TumRgbdSequence(tum40)
    a = seq.association
    assert (a.inputs, a.paired, a.partners, len(seq)) == (N, N - removed, N - removed, N)  # the rgb images stay frames
    assert [d[0] for d in a.dropped] == [names[k] for k in gone]
    assert all(why.startswith("no depth image within 0.02 s (nearest 0.03") for _, why in a.dropped)
    assert sum(d is None for d in seq._depth) == removed and a.shift_s is None
    warned = _warnings(caplog, "have no depth image")
    if removed / N > DROP_WARN_FRACTION:  # 3 of 40 (7.5 %) is, 2 of 40 (5 %) is not
        assert warned == [f"{tum40 / 'depth.txt'}: 3 of 40 rgb images (8 %) have no depth image within 0.02 s (the "
                          f"nearest depth image 0.032 s away); they are frames without depth: {', '.join(name for name, _ in a.dropped)}"]
    else:
        assert warned == []


@pytest.mark.realdata
def test_real_teddy_pairs_without_a_warning(caplog):
    """The control: the full teddy subset leaves 7 of 200 rgb images (3.5 %) without depth, under the threshold."""
    with caplog.at_level(logging.INFO, logger="vslam.data"):
        a = TumRgbdSequence(_need("tum/rgbd_dataset_freiburg3_teddy")).association
    assert (a.inputs, a.paired, len(a.dropped), a.shift_s) == (200, 193, 7, None)
    assert abs(a.median_offset_s) < 1e-3 and [r for r in caplog.records if r.levelname == "WARNING"] == []


# -- EuRoC: left images without a right one are counted and warned about (they were dropped at INFO level) -----


def test_euroc_left_images_without_a_right_one_are_counted_and_named(tmp_path, caplog):
    root = _copy_euroc(tmp_path / "data")
    assert EurocSequence(root).association.dropped == []  # cam1 lists 4 more than cam0: no left frame lost
    csv = root / "mav0" / "cam1" / "data.csv"
    head, rows = _data_lines(csv)
    csv.write_text("\n".join(head + [r for k, r in enumerate(rows) if k % 9 != 4]) + "\n")  # 11 of 95 removed
    caplog.clear()
    seq = EurocSequence(root)
    a = seq.association
    assert (a.kind, a.inputs, a.paired, len(a.dropped), a.unpaired_kept, len(seq)) == ("left-right", 95, 84, 11, False, 84)
    assert a.dropped[0] == ("cam0/data/1403715273462142976.png",
                            "no cam1 image with the same timestamp (nearest 0.050 s away)")
    (w,) = _warnings(caplog, "have no cam1")
    assert w.startswith(f"{root / 'mav0' / 'cam0' / 'data.csv'}: 11 of 95 cam0 (left) images (12 %) have no cam1 "
                        "(right) image with the same timestamp")
    assert "they are dropped: cam0/data/1403715273462142976.png" in w and "and 8 more" in w
    assert a.summary() == ("left-right pairing: 95 left images, 84 with right at the same time, 11 without (dropped; "
                           "first: cam0/data/1403715273462142976.png, no cam1 image with the same timestamp (nearest "
                           "0.050 s away))")


def test_euroc_right_times_that_match_no_left_time_are_an_error(cli, tmp_path):
    root = _copy_euroc(tmp_path / "data")
    csv = root / "mav0" / "cam1" / "data.csv"
    head, rows = _data_lines(csv)
    csv.write_text("\n".join(head + [f"{int(r.split(',')[0]) + 1_000_000},{r.split(',')[1]}" for r in rows]) + "\n")
    rc, _, err = cli("run", "--preset", "euroc_stereo", "--data", root, "-o", tmp_path / "out", *FAST)
    one_error_line(rc, err, "cam1/data.csv: no cam0 image has a cam1 image with the same timestamp (95 cam0 images",
                   "the nearest are 0.001 s apart", "--sensor mono")


# -- a bag: the same rules on its depth topic ----------------------------------------------------------------


@pytest.mark.parametrize("encoding, needle", [("16UC1", None), ("mono8", "depth image is 8-bit (uint8), expected 16UC1")])
def test_bag_depth_topic_is_paired_and_checked(tum40, tmp_path, encoding, needle):
    pytest.importorskip("rosbags", reason="the optional 'bags' extra (rosbags) is not installed")
    from tests.data.make_inputs import write_bag
    from vslam.data.bag import BagSequence
    from vslam.errors import DatasetError

    rgb = [(float(r.split()[0]), tum40 / r.split()[1]) for r in _data_lines(tum40 / "rgb.txt")[1][:6]]
    depth = [(float(r.split()[0]), tum40 / r.split()[1]) for r in _data_lines(tum40 / "depth.txt")[1][:5]]
    if encoding == "mono8":
        _rewrite_depth(tum40, lambda d: (d // 256).astype(np.uint8))
    bag = write_bag(tmp_path / "b.bag", 1, rgb, depth, depth_encoding=encoding)
    if needle is not None:
        with pytest.raises(DatasetError, match=rf"b.bag:/camera/depth/image: {re.escape(needle)}"):
            BagSequence(bag, sensor="rgbd")
        return
    a = BagSequence(bag, sensor="rgbd").association
    assert (a.kind, a.inputs, a.paired, a.partners) == ("rgb-depth", 6, 5, 5)
    assert a.dropped == [(f"/camera/rgb/image_color at {rgb[5][0]:.6f} s", "no depth image within 0.02 s (nearest 0.036 s away)")]
