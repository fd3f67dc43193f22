"""The Rerun logger (vslam.viz.rerun_log): a short SLAM run recorded to an .rrd file and read back; keypoint fates
by hand; rerun never imported with the viewer off; the CLI flags."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest

from vslam.data.trajectory import read_trajectory
from vslam.viz.rerun_log import DYNAMIC, NEW, TRACKED, ViewerConfig, keypoint_fates

N_FRAMES = 20


def test_keypoint_fates_by_hand():
    front = SimpleNamespace(feats=np.zeros((6, 2)))  # len() is all keypoint_fates asks of the keypoints
    # keypoints 1 and 4 dropped by the mask; of the kept 0, 2, 3, 5: 0 and 3 matched, 5 flagged moving
    view = SimpleNamespace(front=front, kept=np.array([0, 2, 3, 5]), point_ids=np.array([7, -1, 9, -1]),
                           moving=np.array([False, False, False, True]))
    np.testing.assert_array_equal(keypoint_fates(view), [TRACKED, DYNAMIC, NEW, TRACKED, DYNAMIC, DYNAMIC])
    # no dynamic filtering, the map's first frame (nothing matched yet)
    view = SimpleNamespace(front=front, kept=None, point_ids=None, moving=None)
    np.testing.assert_array_equal(keypoint_fates(view), [NEW] * 6)


def test_viewer_off_never_imports_rerun(tmp_path):
    code = ("import sys; from vslam.pipeline import Pipeline, PipelineConfig; "
            "cfg = PipelineConfig.load(None, {'tracker': 'baseline', 'dataset': {'synthetic': {'n_frames': 5}}, "
            f"'output': {{'dir': {str(tmp_path)!r}, 'report': False}}}}); "
            "Pipeline(cfg).run(); assert 'rerun' not in sys.modules, 'rerun imported'; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


def test_cli_flags_set_the_viewer_config():
    from vslam.cli.app import _viewer_overrides, build_parser

    args = build_parser().parse_args(["demo", "--viewer", "--rrd", "x.rrd", "--serve"])
    assert _viewer_overrides(args) == {"output": {"viewer": {"spawn": True, "serve": True, "rrd": "x.rrd"}}}
    args = build_parser().parse_args(["run", "--rrd", "y.rrd"])
    assert _viewer_overrides(args) == {"output": {"viewer": {"rrd": "y.rrd"}}}
    assert _viewer_overrides(build_parser().parse_args(["run"])) == {}
    assert not ViewerConfig().enabled and ViewerConfig(rrd="a.rrd").enabled


def _read(path) -> dict[str, list]:
    """entity path -> its logged rows, each a dict column -> value (python objects)."""
    from rerun.chunk import RrdReader

    rows: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path].extend(chunk.to_record_batch().to_pylist())
    for r in rows.values():
        r.sort(key=lambda row: row.get("frame") or -1)
    return rows


def _per_frame_positions(res) -> np.ndarray:
    return read_trajectory(res.paths["trajectory_tum"]).poses[:, :3, 3]


def _col(rows: list, name: str) -> list:
    return [r[name] for r in rows if r.get(name) is not None]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    pytest.importorskip("rerun", reason="rerun-sdk not installed (pip install 'vslam[viewer]')")
    from vslam.pipeline import Pipeline, PipelineConfig

    out = tmp_path_factory.mktemp("rerun")
    # SLAM on the synthetic room, walkers in view from the first frame (seed 1) and masked (exact masks), line
    # segments on: every layer is logged
    cfg = PipelineConfig.load(None, {
        "dataset": {"kind": "synthetic", "sensor": "rgbd", "synthetic": {"n_frames": N_FRAMES, "seed": 1, "n_movers": 6}},
        "slam": {"dynamic": {"enabled": True, "source": "gt_mask"}, "lines": {"enabled": True}},
        "output": {"dir": str(out), "report": False, "viewer": {"rrd": str(out / "run.rrd"), "map_every": 5}}})
    res = Pipeline(cfg).run()
    return res, _read(out / "run.rrd")


def test_recording_has_one_of_each_per_frame(recording):
    res, rows = recording
    assert len(res.trajectory) == N_FRAMES and res.tracked.all()
    every = ["world/camera/image", "world/camera", "status", "stats/ms/total", "stats/ms/features", "stats/ms/viewer",
             "stats/count/inliers", "stats/count/features", "world/camera/image/lines",
             "world/camera/image/dynamic_mask", "world/camera/image/boxes/dataset"]
    every += [f"world/camera/image/keypoints/{f}" for f in ("tracked", "dynamic", "new")]
    for entity in every:
        frames = [r["frame"] for r in rows["/" + entity] if r.get("frame") is not None]
        assert frames == list(range(N_FRAMES)), entity
    images = _col(rows["/world/camera/image"], "EncodedImage:blob")
    assert len(images) == N_FRAMES and bytes(images[0][0][:2]) == b"\xff\xd8"  # JPEG
    assert len(_col(rows["/world/camera/image"], "Pinhole:image_from_camera")) == 1  # static, once
    # the camera's pose each frame is the one trajectory.tum.txt got then (trajectory_final moves with later BA)
    t = np.array(_col(rows["/world/camera"], "Transform3D:translation")).reshape(-1, 3)
    np.testing.assert_allclose(t, _per_frame_positions(res), atol=1e-5)


def test_keypoints_by_fate_match_the_stats(recording):
    res, rows = recording
    count = {f: [len(p) for p in _col(rows[f"/world/camera/image/keypoints/{f}"], "Points2D:positions")]
             for f in ("tracked", "dynamic", "new")}
    n_features = [s["n_features"] for s in res.stats]  # keypoints left after the masks
    n_inliers = [s["n_inliers"] for s in res.stats]
    assert [a + b for a, b in zip(count["tracked"], count["new"])] == n_features
    assert count["tracked"] == n_inliers and sum(n_inliers[1:]) > 0  # the first frame makes the map
    assert all(n > 0 for n in count["dynamic"])  # the walkers' keypoints, masked on every frame


def test_trajectory_map_and_groundtruth(recording):
    res, rows = recording
    strips = _col(rows["/world/trajectory/estimated"], "LineStrips3D:strips")
    # refreshed on frames 0, 5, 10, 15 and at the end: the last holds every pose, in one strip (one map)
    assert len(strips) == N_FRAMES // 5 + 1
    last = strips[-1]
    assert len(last) == 1
    np.testing.assert_allclose(np.array(last[0]), _per_frame_positions(res), atol=1e-5)
    gt = _col(rows["/world/trajectory/groundtruth"], "LineStrips3D:strips")
    assert len(gt) == 1 and len(gt[0][0]) == N_FRAMES
    # anchored at the first estimated pose
    np.testing.assert_allclose(gt[0][0][0], _per_frame_positions(res)[0], atol=1e-6)
    kfs = _col(rows["/world/map/keyframes"], "Points3D:positions")
    n_kf = sum(1 for line in open(res.paths["keyframes"]) if not line.startswith("#"))
    assert len(kfs[-1]) == n_kf >= 2
    assert len(_col(rows["/world/map/points"], "Points3D:positions")[-1]) > 100
    recent = _col(rows["/world/trajectory/recent"], "LineStrips3D:strips")
    assert len(recent) == N_FRAMES - len(strips) + 1  # every frame that did not refresh the full one


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_loops_merges_and_new_maps(tmp_path):
    """A tracker stand-in whose map gains a loop, then a merge, then a second map: edges between the keyframes'
    positions, one event line each, and the trajectory split per map."""
    pytest.importorskip("rerun", reason="rerun-sdk not installed (pip install 'vslam[viewer]')")
    from vslam.data.types import PinholeCamera
    from vslam.viz.rerun_log import RerunLogger

    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    seq = SimpleNamespace(name="stand-in", sensor="rgbd", calibration=SimpleNamespace(cam0=cam),
                          groundtruth=lambda: None)
    kfs = {i: SimpleNamespace(T_world_cam=_pose(float(i))) for i in range(4)}
    tracker = SimpleNamespace(map=SimpleNamespace(keyframes=kfs, points={}), loop=SimpleNamespace(stats=SimpleNamespace(loops=[])),
                              atlas=SimpleNamespace(merges=[]))
    logger = RerunLogger(ViewerConfig(rrd=str(tmp_path / "x.rrd"), map_every=100), seq, tracker, groundtruth=False)
    for k in range(6):
        if k == 2:
            tracker.loop.stats.loops.append((3, 0))
        if k == 3:
            tracker.atlas.merges.append((1, 0, 2, 1))  # map 1 merged into 0, keyframe 2 seen as keyframe 1
        frame = SimpleNamespace(index=k, timestamp=0.1 * k, image=np.zeros((48, 64), np.uint8), boxes=None,
                                dynamic_mask=None)
        est = SimpleNamespace(has_pose=True, T_world_cam=_pose(0.5 * k), map_id=int(k >= 4), status_name="tracked",
                              n_inliers=10, n_features=20, uncertain=False)
        logger.log_frame(frame, est, {"ms_total": 1.0, "n_inliers": 10})
    logger.close()
    rows = _read(tmp_path / "x.rrd")
    loops = _col(rows["/world/map/loops"], "LineStrips3D:strips")
    assert [r["frame"] for r in rows["/world/map/loops"]] == [2]
    np.testing.assert_allclose(np.array(loops[0][0])[:, 0], [3.0, 0.0])
    merges = _col(rows["/world/map/merges"], "LineStrips3D:strips")
    np.testing.assert_allclose(np.array(merges[0][0])[:, 0], [2.0, 1.0])
    events = _col(rows["/events"], "TextLog:text")
    assert events == [["loop: keyframe 3 - keyframe 0"], ["merge: keyframe 2 - keyframe 1"], ["frame 4: map 1 starts"]]
    # the full trajectory, last logged at close: frames 0-3 in map 0, 4-5 in map 1
    last = _col(rows["/world/trajectory/estimated"], "LineStrips3D:strips")[-1]
    assert [len(strip) for strip in last] == [4, 2]


def test_viewer_without_a_display_is_one_error(monkeypatch, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk not installed (pip install 'vslam[viewer]')")
    from vslam.errors import ConfigError
    from vslam.viz.rerun_log import RerunLogger

    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    seq = SimpleNamespace(name="x", sensor="rgbd", groundtruth=lambda: None)
    with pytest.raises(ConfigError, match="needs a display"):
        RerunLogger(ViewerConfig(spawn=True), seq, None, groundtruth=False)
