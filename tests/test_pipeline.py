"""Pipeline end to end on synthetic data: outputs, determinism, faults, no lost output."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import read_trajectory
from vslam.errors import DatasetError
from vslam.pipeline import Pipeline, PipelineConfig


def _cfg(tmp_path, sensor="rgbd", **synth):
    # Pipeline mechanics, checked with the fast baseline tracker; tests/tracking/test_slam.py runs SLAM through it.
    return PipelineConfig.load(None, {"tracker": "baseline", "dataset": {"kind": "synthetic", "sensor": sensor, "synthetic": {"n_frames": 40, **synth}},
                                      "output": {"dir": str(tmp_path)}})


def test_rgbd_run_writes_everything_and_is_accurate(tmp_path):
    res = Pipeline(_cfg(tmp_path)).run()
    assert len(res.trajectory) == 40 and res.tracked.all()
    for key in ("trajectory_tum", "trajectory_kitti", "stats", "config", "groundtruth", "report_html", "metrics"):
        assert res.paths[key].is_file(), key
    back = read_trajectory(res.paths["trajectory_tum"])
    np.testing.assert_allclose(back.poses, res.trajectory.poses, atol=1e-6)
    assert len(read_trajectory(res.paths["trajectory_kitti"])) == 40
    # baseline RGB-D odometry on the synthetic room: measured 0.0063 m over 40 frames (0.57 m path)
    assert res.eval.ate.translation.rmse < 0.0095  # 1.5x the measured value: a doubled error fails
    # the resolved config beside the outputs reloads to the same config
    assert PipelineConfig.load(res.paths["config"]) == _cfg(tmp_path)


def test_stereo_run(tmp_path):
    res = Pipeline(_cfg(tmp_path, sensor="stereo")).run()
    assert res.tracked.all()
    assert res.eval.ate.translation.rmse < 0.0165  # measured 0.011 m (bound 1.5x)


def test_same_input_same_trajectory(tmp_path):
    a = Pipeline(_cfg(tmp_path / "a")).run()
    b = Pipeline(_cfg(tmp_path / "b")).run()
    np.testing.assert_array_equal(a.trajectory.poses, b.trajectory.poses)
    assert (tmp_path / "a" / "trajectory.tum.txt").read_text() == (tmp_path / "b" / "trajectory.tum.txt").read_text()


def test_survives_a_10_frame_blackout(tmp_path):
    res = Pipeline(_cfg(tmp_path, n_frames=50, blackouts=[[20, 10]])).run()
    assert len(res.trajectory) == 50
    assert not res.tracked[20:30].any()  # black frames are marked as predicted, not measured
    assert res.tracked[:20].all() and res.tracked[30:].all()  # and tracking resumes right after
    # measured 0.046 m (the 10 predicted poses dominate); losing the track instead gives metres
    assert res.eval.ate.translation.rmse < 0.07  # 1.5x
    # after the blackout the pose is re-measured against the last good frame (measured 0.036 m)
    assert res.eval.arrays.ate_t[30:].max() < 0.054  # 1.5x


class _Crashing(SyntheticSequence):
    """A sequence whose 13th frame fails like a corrupt disk would."""

    def __iter__(self):
        for k, f in enumerate(super().__iter__()):
            if k == 12:
                raise DatasetError("frame_12.png", "I/O error")
            yield f


def test_no_output_lost_on_crash(tmp_path):
    seq = _Crashing(SyntheticConfig(n_frames=20))
    with pytest.raises(DatasetError):
        Pipeline(_cfg(tmp_path)).run(seq)
    assert len(read_trajectory(tmp_path / "trajectory.tum.txt")) == 12
    assert len((tmp_path / "stats.csv").read_text().splitlines()) == 13  # header + 12 rows


def test_networks_get_the_cores_the_tracking_thread_leaves_and_threads_are_restored(tmp_path, monkeypatch):
    import torch

    import vslam.pipeline as pl

    seq = SyntheticSequence(SyntheticConfig(n_frames=3, width=160, height=120, n_movers=0), sensor="rgbd")
    seen: list[int] = []
    before = torch.get_num_threads()
    monkeypatch.setattr(pl, "usable_cpus", lambda: 3)
    for front_thread, threads, want in ((True, 0, 2), (False, 0, 3), (True, 1, 1)):
        seen.clear()
        cfg = PipelineConfig.load(None, {"tracker": "slam", "output": {"dir": str(tmp_path), "report": False},
                                         "slam": {"frontend_thread": front_thread, "torch_threads": threads}})
        Pipeline(cfg).run(seq, progress=lambda k, n: seen.append(torch.get_num_threads()))
        assert seen == [want] * 3
        assert torch.get_num_threads() == before


def test_run_limits_numpy_blas_threads_and_the_ba_worker_follows():
    """SlamConfig.blas_threads caps numpy's BLAS threads while a run lasts (restored after); the async BA worker
    process started meanwhile gets the same cap."""
    from threadpoolctl import threadpool_info

    from tests._proc import environ_after_exec
    from vslam.backend.worker import BAWorker
    from vslam.pipeline import blas_threads
    from vslam.tracking.slam import SlamConfig

    def counts():
        return [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]

    before = counts()
    assert before
    with blas_threads(SlamConfig(blas_threads=1)):
        assert counts() == [1] * len(before)
        w = BAWorker()
        w.start()
        try:
            env = environ_after_exec(w._proc.pid, b"vslam.backend.worker")
            assert b"OPENBLAS_NUM_THREADS=1" in env
        finally:
            w.close()
    assert counts() == before
    with blas_threads(SlamConfig(blas_threads=0)):
        assert counts() == before
