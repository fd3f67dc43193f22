"""Issue 3, bad input / faults: blurred frames, a 10-frame blackout, frames without depth and a duplicate
timestamp in one synthetic RGB-D run through the pipeline (SLAM tracker). The run keeps going, marks those
frames in stats.csv (status, uncertain, pose std) and writes a trajectory every reader accepts."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import read_trajectory
from vslam.pipeline import Pipeline, PipelineConfig

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)
N = 54
BLUR = range(8, 13)  # Gaussian blur, sigma 8 px: ~100 corners left, too few to track
NO_DEPTH = range(18, 23)  # depth sensor dropout
BLACK = range(30, 40)  # 10 black frames
DUP = 47  # stamped with frame 46's time


class _Faulty(SyntheticSequence):
    """The synthetic room with depth dropped on NO_DEPTH and frame DUP carrying the previous timestamp."""

    def __iter__(self):
        prev = None
        for f in super().__iter__():
            if f.index in NO_DEPTH:
                f.depth = None
            if f.index == DUP:
                f = dataclasses.replace(f, timestamp=prev)
            prev = f.timestamp
            yield f


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("faults")
    scfg = SyntheticConfig(n_frames=N, blurs=((BLUR.start, len(BLUR)),), blur_sigma=8.0,
                           blackouts=((BLACK.start, len(BLACK)),), **SMALL)
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic", "sensor": "rgbd"},
                                     "output": {"dir": str(out), "report": False}})
    res = Pipeline(cfg).run(_Faulty(scfg))
    with open(out / "stats.csv", newline="") as f:
        rows = {int(r["index"]): r for r in csv.DictReader(f)}
    return res, rows, out


def _col(rows, name, idx):
    return [rows[i][name] for i in idx]


def test_faulty_frames_are_marked_uncertain(run):
    _, rows, _ = run
    assert len(rows) == N
    for idx in (BLUR, BLACK):  # not measured: predicted by constant velocity, std unknown
        assert set(_col(rows, "status", idx)) == {"predicted"}
        assert set(_col(rows, "uncertain", idx)) == {"1"} and set(_col(rows, "tracked", idx)) == {"0"}
        assert set(_col(rows, "pose_std_m", idx)) == {"nan"}
    # without depth the frame is still measured from 2-D matches to the map, but marked and weaker
    assert set(_col(rows, "status", NO_DEPTH)) == {"no_depth"} and set(_col(rows, "uncertain", NO_DEPTH)) == {"1"}
    assert rows[DUP]["status"] == "duplicate_time" and rows[DUP]["uncertain"] == "1"
    good = [i for i in range(N) if i not in BLUR and i not in BLACK and i not in NO_DEPTH and i != DUP]
    assert set(_col(rows, "status", good)) <= {"tracked", "relocalised"} and set(_col(rows, "uncertain", good)) == {"0"}
    std_good = np.array(_col(rows, "pose_std_m", good[1:]), float)
    assert float(rows[0]["pose_std_m"]) == 0.0  # the first frame defines the world
    # measured 4-12 mm (300-800 inliers at 1 px; first order, map points taken as exact)
    assert np.all(np.isfinite(std_good)) and np.all(std_good > 1e-3) and np.all(std_good < 0.03)
    # without depth each inlier carries less: std x sqrt(inliers) measured 0.156-0.171 vs 0.115-0.129 m on
    # the 5 frames before
    def per_inlier(idx):
        return np.array(_col(rows, "pose_std_m", idx), float) * np.sqrt(np.array(_col(rows, "n_inliers", idx), float))

    before = range(NO_DEPTH.start - 5, NO_DEPTH.start)
    assert np.min(per_inlier(NO_DEPTH)) > 1.1 * np.median(per_inlier(before))


def test_tracking_resumes_after_each_fault_and_stays_accurate(run):
    res, rows, _ = run
    resumed = [i for i in range(N) if i not in BLUR and i not in BLACK and i != DUP]
    assert set(_col(rows, "tracked", resumed)) == {"1"}  # measured again right after each fault
    ate = res.eval.ate.translation.rmse
    assert ate < 0.04, ate  # bound 1.5x; measured 0.027 m over 0.8 m; the predicted poses dominate it
    after = res.trajectory.timestamps >= float(rows[BLACK.stop]["timestamp"])
    assert res.eval.arrays.ate_t[after].max() < 0.05  # re-measured after the blackout


def test_duplicate_timestamp_leaves_a_readable_trajectory(run):
    res, rows, out = run
    assert len(res.trajectory) == N - 1  # every frame but the duplicate
    back = read_trajectory(out / "trajectory.tum.txt")  # the reader rejects non-increasing time
    assert len(back) == N - 1 and np.all(np.diff(back.timestamps) > 0)
    assert len(read_trajectory(out / "trajectory.kitti.txt")) == N - 1
