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

    import vslam.pipeline.runtime as pl

    seq = SyntheticSequence(SyntheticConfig(n_frames=3, width=160, height=120, n_movers=0), sensor="rgbd")
    seen: list[int] = []
    before = torch.get_num_threads()
    monkeypatch.setattr(pl, "usable_cpus", lambda: 3)
    for front_thread, threads, want in ((True, 0, 2), (False, 0, 3), (True, 1, 1)):
        seen.clear()
        cfg = PipelineConfig.load(None, {"tracker": "slam", "output": {"dir": str(tmp_path), "report": False},
                                         "runtime": {"frontend_thread": front_thread, "torch_threads": threads}})
        Pipeline(cfg).run(seq, progress=lambda k, n: seen.append(torch.get_num_threads()))
        assert seen == [want] * 3
        assert torch.get_num_threads() == before


def test_run_limits_numpy_blas_threads_and_the_ba_worker_follows():
    """RuntimeConfig.blas_threads caps numpy's BLAS threads while a run lasts (restored after); the async BA worker
    process started meanwhile gets the same cap."""
    from threadpoolctl import threadpool_info

    from tests._proc import environ_after_exec
    from vslam.backend.worker import BAWorker
    from vslam.pipeline import blas_threads
    from vslam.runtime import RuntimeConfig

    def counts():
        return [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]

    before = counts()
    assert before
    with blas_threads(RuntimeConfig(blas_threads=1)):
        assert counts() == [1] * len(before)
        w = BAWorker()
        w.start()
        try:
            env = environ_after_exec(w._proc.pid, b"vslam.backend.worker")
            assert b"OPENBLAS_NUM_THREADS=1" in env
        finally:
            w.close()
    assert counts() == before
    with blas_threads(RuntimeConfig(blas_threads=0)):
        assert counts() == before


def test_alignment_follows_whether_the_scale_is_observed(tmp_path):
    """align: auto scores a run without metric scale (monocular) with Sim3 and one in metres with SE3, and the
    report says which; an explicit SE3 on a monocular run is honoured with a note. Catches a monocular ATE that
    mixes the unknown scale into the error (what an SE3 default did)."""
    import json

    mono = Pipeline(_cfg(tmp_path / "mono", sensor="mono")).run()
    assert not mono.metric_scale and mono.eval.alignment.method == "sim3" and "(sim3, scale " in mono.eval.summary()
    metrics = json.loads(mono.paths["metrics"].read_text())
    assert metrics["alignment"]["method"] == "sim3" and metrics["run"]["metric_scale"] is False
    assert "scale not observable (monocular)" in mono.paths["report_md"].read_text()
    rgbd = Pipeline(_cfg(tmp_path / "rgbd")).run()
    assert rgbd.metric_scale and rgbd.eval.alignment.method == "se3" and "(se3)" in rgbd.eval.summary()
    forced = PipelineConfig.load(None, {"tracker": "baseline", "eval": {"align": "se3"},
                                        "dataset": {"kind": "synthetic", "sensor": "mono", "synthetic": {"n_frames": 40}},
                                        "output": {"dir": str(tmp_path / "forced")}})
    se3 = Pipeline(forced).run()
    assert se3.eval.alignment.method == "se3" and any("without metric scale" in n for n in se3.eval.notes)


def test_every_preset_scores_a_monocular_run_with_sim3():
    """A preset made for depth or stereo, run with --sensor mono, must not force SE3 on it (align: auto)."""
    from vslam.resources import preset_names, preset_path

    for name in preset_names():
        cfg = PipelineConfig.load(preset_path(name))
        assert cfg.eval.resolve_align(monocular=True) == "sim3", name
        assert cfg.eval.resolve_align(monocular=False) in ("se3", "sim3"), name


def test_a_monocular_map_scaled_by_the_imu_is_metric():
    from vslam.tracking.slam import SlamConfig, SlamTracker
    from vslam.tracking.vio import VioConfig

    seq = SyntheticSequence(SyntheticConfig(n_frames=2, width=320, height=240, fx=262.5, fy=262.5))
    st = SlamTracker(seq.calibration, "mono", SlamConfig(inertial=VioConfig(enabled=True)))
    assert not st.metric_scale  # before the visual-inertial alignment the scale is the two-view map's
    st.vio.ready = True
    assert st.metric_scale
    assert SlamTracker(seq.calibration, "rgbd", SlamConfig()).metric_scale


def test_skipped_frames_are_the_holes_the_readers_list_and_a_missing_tail():
    """Frames a reader could not decode are counted whichever process read them: holes in the indices that
    reached tracking (a front-end child skips silently for us), the reader's own list, and a tail when reading
    stopped before the frames asked for. Frames left out on purpose (stride, drop) are not skipped."""
    from types import SimpleNamespace

    from vslam.pipeline import skipped_frames

    class Seq(SimpleNamespace):
        def __len__(self):
            return 10

    assert skipped_frames(Seq(skipped=[]), list(range(10)), 10) == []
    assert skipped_frames(Seq(skipped=[]), [0, 1, 3, 4], 5) == [2]  # a hole
    assert skipped_frames(Seq(skipped=[(9, "x")]), [0, 1, 2], 10) == [3, 4, 5, 6, 7, 8, 9]  # stopped early
    stride = Seq(skipped=[(4, "bad")], indices=np.array([0, 2, 4, 6, 8]))
    assert skipped_frames(stride, [0, 2, 6, 8], 5) == [4]
    assert skipped_frames(Seq(skipped=[]), [0, 1, 2], 3) == []  # max_frames: nothing missing
    # a reader that found a lost frame beyond where the run stopped (--max-frames) does not count it
    assert skipped_frames(Seq(skipped=[(3, "bad"), (9, "bad")]), [0, 1, 2, 4, 5], 5) == [3]
