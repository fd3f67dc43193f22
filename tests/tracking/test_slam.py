"""The SLAM tracker end to end on small synthetic sequences (320x240, static scene)."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import Trajectory
from vslam.eval import EvalConfig, evaluate
from vslam.pipeline import Pipeline, PipelineConfig
from vslam.runtime import RuntimeConfig
from vslam.tracking.initializer import InitConfig
from vslam.tracking.slam import SlamConfig, SlamTracker

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)


def _seq(sensor, n=60, **kw):
    return SyntheticSequence(SyntheticConfig(n_frames=n, **{**SMALL, **kw}), sensor=sensor)


def _run(seq, sensor, frames=None, cfg=SlamConfig()):
    st = SlamTracker(seq.calibration, sensor, cfg)
    stamps, poses, tracked = [], [], []
    for f in frames if frames is not None else seq:
        e = st.track(f)
        stamps.append(f.timestamp), poses.append(e.T_world_cam), tracked.append(e.tracked)
    return st, Trajectory(np.array(stamps), np.array(poses)), np.array(tracked)


def _ate(traj, seq, mono=False):
    return evaluate(traj, seq.groundtruth(), EvalConfig(align="sim3" if mono else "se3"), monocular=mono)


def test_rgbd_pipeline_accuracy_keyframes_and_map(tmp_path):
    cfg = PipelineConfig.load(None, {"tracker": "slam", "dataset": {"kind": "synthetic", "sensor": "rgbd",
                                     "synthetic": {"n_frames": 60, **SMALL}}, "output": {"dir": str(tmp_path), "report": False}})
    res = Pipeline(cfg).run()
    assert res.tracked.all()
    # measured 0.0056 m over 0.89 m of path (baseline odometry: 0.012 m)
    assert res.eval.ate.translation.rmse < 0.0085  # 1.5x the measured value
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(str(res.paths["map"]))
    assert len(pcd.points) > 500
    kf = np.loadtxt(res.paths["keyframes"])
    assert kf.ndim == 2 and kf.shape[1] == 8 and len(kf) >= 2


def test_stereo_accuracy():
    seq = _seq("stereo")
    _, traj, tracked = _run(seq, "stereo")
    assert tracked.all()
    # measured 0.018 m here (0.014 m where the bound was first set; scene seeds 1000 / 2000: 0.007 / 0.013 m; the
    # same to 1e-15 with 1 CPU and single-threaded BLAS); bound 1.5x: a doubled error (depth from a wrong baseline
    # or disparity, local BA off) fails
    assert _ate(traj, seq).ate.translation.rmse < 0.027


def test_survives_a_10_frame_blackout():
    seq = _seq("rgbd", 50, blackouts=((20, 10),))
    st, traj, tracked = _run(seq, "rgbd")
    assert not tracked[20:30].any()  # black frames are predicted, not measured
    assert tracked[:20].all() and tracked[30:].all()  # relocalised right after
    res = _ate(traj, seq)
    assert res.ate.translation.rmse < 0.045  # measured 0.03 m (bound 1.5x), dominated by the predicted frames
    assert res.arrays.ate_t[30:].max() < 0.05


def test_same_input_same_poses():
    seq = _seq("rgbd", 30)
    frames = list(seq)
    _, a, _ = _run(seq, "rgbd", frames)
    _, b, _ = _run(seq, "rgbd", frames)
    np.testing.assert_array_equal(a.poses, b.poses)


def test_frames_without_depth_and_duplicates_do_not_crash():
    seq = _seq("rgbd", 30)
    frames = list(seq)
    for f in frames[10:15]:
        f.depth = None
    frames.insert(20, frames[19])  # a duplicated frame (same timestamp)
    st, traj, tracked = _run(seq, "rgbd", frames)
    assert len(traj) == 31 and tracked[:10].all() and tracked[25:].all()
    assert st.map_stats()["keyframes"] >= 1


def test_monocular_after_initialisation():
    seq = _seq("mono", 60)
    # the room's first views are near-planar; prefer the essential matrix (as configs/kitti_mono.yaml does)
    cfg = SlamConfig(init=InitConfig(h_ratio=0.9, planar_inlier_ratio=1.01))
    _, traj, tracked = _run(seq, "mono", cfg=cfg)
    first = int(np.argmax(tracked))
    assert tracked.any() and first < 30, "monocular map never initialised"
    assert tracked[first:].all()
    sub = traj.subset(np.arange(first, len(traj)))
    rmse = _ate(sub, seq, mono=True).ate.translation.rmse
    # bound 1.5x; measured 0.047 m (Sim3) over 0.75 m, initialised at frame 7 (0.036 m when first written, 0.042 m at
    # the commit that set the bound 0.054; scene seeds 1000 / 2000: 0.014 / 0.035 m; the same to 1e-8 with 1 CPU and
    # single-threaded BLAS). Catches a broken initialisation or scale drift (a doubled error)
    assert rmse < 0.07, rmse


def _mapping(lag: int) -> SlamConfig:
    from dataclasses import replace

    base = SlamConfig()
    return replace(base, mapping=replace(base.mapping, ba_lag_frames=lag))


def test_local_ba_in_the_worker_process_keeps_the_trajectory(tmp_path):
    seq = _seq("rgbd", 40)
    frames = list(seq)
    st0, sync, _ = _run(seq, "rgbd", frames)
    st1, lag1, _ = _run(seq, "rgbd", frames, _mapping(1))
    kf_frames = {k.frame_index for k in st1.map.keyframes.values()}
    assert 3 <= len(kf_frames) == len(st0.map.keyframes)
    # lag 1: written back before the next frame is tracked, so every frame after a keyframe is tracked on the
    # very map the in-process BA gives; only a keyframe's own online pose is from before its BA
    for i, f in enumerate(frames):
        if f.index not in kf_frames:
            np.testing.assert_array_equal(lag1.poses[i], sync.poses[i])
    for k in st0.map.keyframes:
        np.testing.assert_allclose(st1.map.keyframes[k].T_world_cam, st0.map.keyframes[k].T_world_cam, atol=1e-12)
    # a long lag (written back when the next keyframe is wanted): deterministic, as accurate
    st2, lagged, tracked = _run(seq, "rgbd", frames, _mapping(30))
    _, again, _ = _run(seq, "rgbd", frames, _mapping(30))
    np.testing.assert_array_equal(lagged.poses, again.poses)
    assert tracked.all()
    a_sync, a_lag = _ate(sync, seq).ate.translation.rmse, _ate(lagged, seq).ate.translation.rmse
    assert a_lag < 1.3 * a_sync + 1e-3, (a_lag, a_sync)
    st2.finish(tmp_path)  # writes the last BA back and stops the worker
    assert st2.mapper.pending is None and st2.mapper.worker is None
    st1.mapper.close()


def test_front_end_computed_ahead_gives_the_same_trajectory(tmp_path):
    """``vslam run`` computes keypoints, stereo depth and line segments on its prefetch thread: the poses must
    be the very ones ``track`` computes by itself (a stereo rig with lines exercises all three)."""
    from dataclasses import replace

    cfg = SlamConfig()
    cfg = replace(cfg, lines=replace(cfg.lines, enabled=True))
    seq = _seq("stereo", 25)
    _, inline, _ = _run(seq, "stereo", cfg=cfg)
    st = SlamTracker(seq.calibration, "stereo", cfg)
    ahead = [st.track(f, st.frontend(f)).T_world_cam for f in seq]
    np.testing.assert_array_equal(np.array(ahead), inline.poses)
    st = SlamTracker(seq.calibration, "stereo", cfg, runtime=RuntimeConfig(lines_beside_networks=True))  # LSD on a thread of its own
    assert st._stage("lines").pool is not None
    beside = [st.track(f, st.frontend(f)).T_world_cam for f in seq]
    st.finish(tmp_path / "beside")
    np.testing.assert_array_equal(np.array(beside), inline.poses)
    runs = {}
    for on in (True, False):
        pc = PipelineConfig.load(None, {"dataset": {"kind": "synthetic", "sensor": "rgbd", "synthetic": {"n_frames": 20, **SMALL}},
                                        "runtime": {"frontend_thread": on}, "output": {"dir": str(tmp_path / str(on)), "report": False}})
        runs[on] = Pipeline(pc).run()
    np.testing.assert_array_equal(runs[True].trajectory.poses, runs[False].trajectory.poses)


def test_detector_run_ahead_on_the_prefetch_thread_gives_the_same_trajectory(tmp_path):
    """With ``slam.dynamic.source=detector`` the network runs on the prefetch thread (``FrontEnd.objects``); the
    poses must be those of the run that detects on the tracking thread, and the stage is timed on its own."""
    import csv

    runs = {}
    for on in (True, False):
        pc = PipelineConfig.load(None, {
            "dataset": {"kind": "synthetic", "sensor": "rgbd", "synthetic": {"n_frames": 15, **SMALL, "n_movers": 3}},
            "runtime": {"frontend_thread": on},
            "slam": {"dynamic": {"enabled": True, "source": "detector", "weights": "models/detector_esea_synth_tiny.pt"}},
            "output": {"dir": str(tmp_path / str(on)), "report": False}})
        runs[on] = Pipeline(pc).run()
        with open(tmp_path / str(on) / "stats.csv", newline="") as f:
            assert all(float(r["ms_detector"]) > 0 for r in csv.DictReader(f))
    np.testing.assert_array_equal(runs[True].trajectory.poses, runs[False].trajectory.poses)


def test_local_map_is_gathered_again_after_any_map_change():
    seq = _seq("rgbd", 12)
    st, _, _ = _run(seq, "rgbd")
    tr, ref = st.tracker, st.ref_kf
    a = tr.local_points(ref)
    assert tr.local_points(ref) is a  # unchanged map: the same local map, not gathered again
    pid = int(a.ids[0])
    st.map.apply_adjustment({}, {pid: st.map.points[pid].xyz + 1.0}, np.ones(0, bool), [], [])
    b = tr.local_points(ref)
    assert b is not a
    np.testing.assert_array_equal(b.xyz[0], a.xyz[0] + 1.0)
    st.map.points[pid].xyz = st.map.points[pid].xyz - 1.0  # a direct write must say so
    st.map.touch()
    np.testing.assert_allclose(tr.local_points(ref).xyz[0], a.xyz[0], atol=1e-12)
    st.map.remove_point(pid)
    assert pid not in tr.local_points(ref).ids


def test_first_round_matches_the_previous_frames_points_and_falls_back_to_the_local_map(monkeypatch):
    """``first_round_last_frame`` (off by default): the motion-model round searches only the points the previous
    frame tracked (ORB-SLAM's TrackWithMotionModel); too few of them, or a frame after a loss, and it searches
    the whole local map, as it always does by default."""
    from dataclasses import replace

    from vslam.tracking.tracker import Tracker

    seq = _seq("rgbd", 12)
    frames = list(seq)
    cfg = SlamConfig()
    st, _, tracked = _run(seq, "rgbd", frames[:11], replace(cfg, tracking=replace(cfg.tracking, first_round_last_frame=True)))
    assert tracked.all() and st._last_ids is not None and len(st._last_ids) >= st.cfg.tracking.min_matches
    searched: list[int] = []
    real = Tracker.search_local
    monkeypatch.setattr(Tracker, "search_local", lambda self, T, local, *a: searched.append(len(local.ids)) or real(self, T, local, *a))
    n_local = len(st.tracker.local_points(st.ref_kf).ids)
    last = st._last_ids
    assert len(last) < n_local
    front = st.frontend(frames[11])
    feats = front.feats
    ur = np.full(len(feats), np.nan)  # monocular rows suffice here
    res = st.tracker.track(feats, ur, st.T_world_cam, st.ref_kf, after_loss=False, last_ids=last)
    assert res.ok and searched == [len(last), n_local]  # round one on the last frame's points, round two: local map
    searched.clear()
    st.tracker.track(feats, ur, st.T_world_cam, st.ref_kf, after_loss=False, last_ids=last[:5])  # too few
    assert searched[0] == n_local
    searched.clear()
    st.tracker.track(feats, ur, st.T_world_cam, st.ref_kf, after_loss=True, last_ids=last)  # after a loss
    assert searched[0] == n_local
    searched.clear()
    off = Tracker(st.map, st.tracker.cam, st.tracker.stereo_cam, SlamConfig().tracking, st.tracker.backend)
    off.track(feats, ur, st.T_world_cam, st.ref_kf, after_loss=False, last_ids=last)  # the default: local map
    assert searched[0] == n_local
