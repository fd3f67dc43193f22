"""Map save / load round trip and localisation-only tracking on a saved map."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vslam.geometry.se3 import inv_T
from vslam.loop.closing import save_slam_map
from vslam.loop.mapio import FORMAT_VERSION, MapFileError, load_map
from vslam.tracking.slam import SlamConfig, SlamTracker
from tests.loop._map import room_map, seq


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    st, frames, poses = room_map()
    return save_slam_map(st, tmp_path_factory.mktemp("map") / "map.vslam.npz")


def test_round_trip_is_exact(saved):
    st, _, _ = room_map()
    loaded = load_map(saved)
    m, m2 = st.map, loaded.map
    assert loaded.header["version"] == FORMAT_VERSION and loaded.header["keyframes"] == len(m.keyframes)
    assert list(m2.keyframes) == list(m.keyframes) and list(m2.points) == list(m.points)
    for k, kf in m.keyframes.items():
        k2 = m2.keyframes[k]
        np.testing.assert_array_equal(k2.T_world_cam, kf.T_world_cam)
        np.testing.assert_array_equal(k2.features.desc, kf.features.desc)
        np.testing.assert_array_equal(k2.point_ids, kf.point_ids)
        np.testing.assert_array_equal(k2.ur, kf.ur)
    for p, mp in m.points.items():
        assert m2.points[p].observations == mp.observations
        np.testing.assert_array_equal(m2.points[p].xyz, mp.xyz)
    assert m2.stats() == m.stats()
    assert (m2._next_kf, m2._next_pt) == (m._next_kf, m._next_pt)
    assert len(loaded.database) == len(m.keyframes)


def test_localise_on_saved_map_reproduces_poses(saved):
    st, frames, poses = room_map()
    n_kf = len(st.map.keyframes)
    last_kf_frame = max(k.frame_index for k in st.map.keyframes.values())
    cfg = dataclasses.replace(SlamConfig(), load_map=str(saved), localize_only=True)
    s = seq()
    loc = SlamTracker(s.calibration, "rgbd", cfg)
    start = 15  # not the first frame: the first pose comes from place recognition over the saved keyframes
    out = np.array([loc.track(f).T_world_cam for f in frames[start:]])
    assert len(loc.map.keyframes) == n_kf  # localisation only: the map is not extended
    # After the last keyframe the SLAM run tracked against exactly the map that was saved: same poses.
    after = np.arange(start, len(frames)) > last_kf_frame + 1
    assert after.sum() >= 5
    np.testing.assert_allclose(out[after, :3, 3], poses[start:][after, :3, 3], atol=1e-4)
    # Before it the SLAM map was still changing; the localised poses are as close to the truth (map frame =
    # first camera) as the SLAM run's (measured: at most 3.8 cm for both, this short run's drift).
    gt = s.groundtruth().poses
    G = np.array([inv_T(gt[0]) @ g for g in gt])[start:]
    err_loc = np.linalg.norm(out[:, :3, 3] - G[:, :3, 3], axis=1)
    err_slam = np.linalg.norm(poses[start:, :3, 3] - G[:, :3, 3], axis=1)
    assert err_loc.max() < max(0.05, 1.5 * err_slam.max())


def test_bad_files_are_reported(tmp_path):
    with pytest.raises(MapFileError, match="not found"):
        load_map(tmp_path / "none.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, header=np.frombuffer(b'{"format": "other", "version": 1}', np.uint8))
    with pytest.raises(MapFileError, match="format"):
        load_map(bad)


def test_damaged_files_are_one_line_errors(saved, tmp_path):
    """A truncated file, a right header over missing arrays: MapFileError naming the file, never a traceback."""
    cut = tmp_path / "cut.npz"
    cut.write_bytes(saved.read_bytes()[:2000])
    with pytest.raises(MapFileError, match="cut.npz: not a vslam map file"):
        load_map(cut)
    with np.load(saved, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files if k != "kf_offset"}
    gap = tmp_path / "gap.npz"
    np.savez(gap, **arrays)
    with pytest.raises(MapFileError, match="gap.npz: corrupt map file"):
        load_map(gap)


def test_saved_map_continues_with_lines_on(saved):
    """Map files hold points only; with lines on, the loaded map gets fresh line landmarks on its own
    keyframes (the line half must use the loaded map, not the empty one it was built with)."""
    from vslam.features.lines import LineConfig

    st0, frames, poses = room_map()
    cfg = dataclasses.replace(SlamConfig(), load_map=str(saved), lines=LineConfig(enabled=True, min_length_px=15.0))
    s = seq(60)
    st = SlamTracker(s.calibration, "rgbd", cfg)
    assert st.lines.map is st.map
    out = np.array([st.track(f).T_world_cam for f in list(s)[15:]])  # past the saved frames: new keyframes
    assert len(st.map.keyframes) > len(st0.map.keyframes) and st.lines.stats()["lines"] > 0
    np.testing.assert_allclose(out[:25, :3, 3], poses[15:40, :3, 3], atol=0.03)


def test_sensor_header_is_compared_on_load(tmp_path):
    """A map made by another camera, keypoint type or (monocular) without scale is refused in one line."""
    from vslam.data.types import PinholeCamera
    from vslam.loop.mapio import MapFileError, check_sensor, sensor_header

    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    rgbd = sensor_header("rgbd", cam, "orb")
    check_sensor("m.npz", {"sensor": rgbd}, rgbd)
    check_sensor("m.npz", {"sensor": rgbd}, sensor_header("mono", cam, "orb"))  # a metric map serves mono
    check_sensor("m.npz", {"sensor": rgbd}, sensor_header("rgbd", PinholeCamera(640, 480, 526.0, 525.0, 319.5, 239.5), "orb"))
    with pytest.raises(MapFileError, match="m.npz: map made by another camera: fx 525, this run's camera 540"):
        check_sensor("m.npz", {"sensor": rgbd}, sensor_header("rgbd", PinholeCamera(640, 480, 540.0, 525.0, 319.5, 239.5), "orb"))
    with pytest.raises(MapFileError, match="monocularly has no metric scale; this run is stereo"):
        check_sensor("m.npz", {"sensor": sensor_header("mono", cam, "orb")}, sensor_header("stereo", cam, "orb"))
    with pytest.raises(MapFileError, match="with 'orb' keypoints, this run uses 'convpoint'"):
        check_sensor("m.npz", {"sensor": rgbd}, sensor_header("rgbd", cam, "convpoint"))
    check_sensor("m.npz", {}, rgbd)  # a file from before the header held the sensor: accepted, with a warning


def test_pose_links_round_trip(tmp_path):
    from vslam.mapping.map import PoseLink

    st, _, _ = room_map()
    ks = sorted(st.map.keyframes)
    T = inv_T(st.map.keyframes[ks[0]].T_world_cam) @ st.map.keyframes[ks[1]].T_world_cam
    cov = np.diag(np.arange(1.0, 7.0)) * 1e-4
    st.map.links.append(PoseLink(ks[0], ks[1], T, cov))
    m2 = load_map(save_slam_map(st, tmp_path / "m.vslam.npz")).map
    assert [(ln.a, ln.b) for ln in m2.links] == [(ks[0], ks[1])]
    np.testing.assert_array_equal(m2.links[0].T_a_b, T)
    np.testing.assert_array_equal(m2.links[0].cov, cov)
    st.map.links.clear()  # room_map() is cached: leave it as it was


def test_every_part_works_on_the_loaded_map(saved):
    """The saved map replaces the empty one everywhere it is referenced (``SlamTracker.use_map``): tracker,
    mapper, frame log, loop closer and the stages (the IMU stage included)."""
    from vslam.tracking.vio import VioConfig

    s = seq(20)
    cfg = dataclasses.replace(SlamConfig(), load_map=str(saved), inertial=VioConfig(enabled=True))
    st = SlamTracker(s.calibration, "rgbd", cfg)
    assert len(st.map.keyframes) > 0
    assert all(m is st.map for m in (st.tracker.map, st.mapper.map, st.frames.map, st.loop.map, st.vio.map))
