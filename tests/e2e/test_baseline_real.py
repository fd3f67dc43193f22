"""The baseline odometry end to end on the real subsets (short prefixes; CI has the data)."""

import numpy as np
import pytest

from vslam.data.registry import open_sequence
from vslam.pipeline import Pipeline, PipelineConfig

pytestmark = pytest.mark.realdata


def _run(seq, sensor, tmp_path, n, align="se3"):
    cfg = PipelineConfig.load(None, {"tracker": "baseline", "dataset": {"sensor": sensor, "max_frames": n}, "eval": {"align": align},
                                     "output": {"dir": str(tmp_path), "report": False}})
    return Pipeline(cfg).run(seq)


def test_tum_teddy_rgbd_60_frames(tum_teddy, tmp_path):
    res = _run(open_sequence(tum_teddy), "rgbd", tmp_path, 60)
    assert len(res.trajectory) == 60 and res.tracked.all()
    # measured 0.0043 m on this prefix; 3x margin for platform noise in OpenCV
    assert res.eval.ate.translation.rmse < 0.012
    lines = [ln for ln in (tmp_path / "trajectory.tum.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 60


def test_euroc_static_window_stereo(euroc_v101, tmp_path):
    res = _run(open_sequence(euroc_v101, sensor="stereo"), "stereo", tmp_path, 40)
    assert res.tracked.all()
    # the camera barely moves (1.7 cm over 95 frames): the estimate must stay within a few mm of it
    drift = np.linalg.norm(res.trajectory.positions[-1] - res.trajectory.positions[0])
    assert drift < 0.02
    assert res.eval.ate.translation.rmse < 0.0047  # bound 1.5x; measured 0.0031 m


def test_kitti_mono_runs(kitti_root, tmp_path):
    res = _run(open_sequence(kitti_root / "sequences" / "07", sensor="mono"), "mono", tmp_path, 40, align="sim3")
    # measured 36 of 39 frames (0.92; the same with 1 CPU and single-threaded BLAS): > 0.9 left one frame to an
    # OpenCV RANSAC that differs by version; losing 8 or more of the 39 frames fails
    assert res.tracked[1:].mean() > 0.8, res.tracked
    assert res.eval.alignment.method == "sim3"
    assert res.eval.ate.translation.rmse < 0.69  # bound 1.5x; measured 0.46 m over 32 m (unit-step mono baseline)
