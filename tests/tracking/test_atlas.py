"""Issue 38: a new map when tracking is lost, maps merged when they meet (``vslam.tracking.atlas``)."""

from __future__ import annotations

import copy
import csv
from dataclasses import replace

import numpy as np
import pytest

from vslam.data.select import select_frames
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import read_trajectory
from vslam.features.depth import stereo_ur
from vslam.geometry.se3 import inv_T, make_T
from vslam.loop.descriptor import make_place_descriptor
from vslam.loop.mapio import load_map
from vslam.mapping.map import Map
from vslam.pipeline import Pipeline, PipelineConfig
from vslam.tracking.atlas import Atlas
from vslam.tracking.slam import SlamConfig, SlamTracker

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _run(seq, cfg: PipelineConfig, out):
    res = Pipeline(cfg).run(seq, out_dir=out)
    with open(out / "stats.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return res, rows


@pytest.fixture(scope="module")
def room_tracker():
    """The synthetic room's first 30 frames tracked (RGB-D): one map with a handful of keyframes."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=30, **SMALL))
    st = SlamTracker(seq.calibration, "rgbd", SlamConfig())
    for f in seq:
        assert st.track(f).tracked
    return st


def test_successor_continues_ids_and_absorb_moves_the_other_map(room_tracker):
    a = room_tracker.map
    b = a.successor()
    assert not b.keyframes and (b._next_kf, b._next_pt) == (a._next_kf, a._next_pt)
    src = copy.deepcopy(a)
    kf_ids, pt_ids = sorted(src.keyframes), sorted(src.points)
    # renumber the copy so that it could be a later map of the same run
    other = Map()
    off_k, off_p = a._next_kf, a._next_pt
    T = make_T(_rot_z(25.0), np.array([1.0, -0.5, 0.2]))
    for k in kf_ids:
        kf = src.keyframes[k]
        kf.id, kf.point_ids = k + off_k, np.where(kf.point_ids >= 0, kf.point_ids + off_p, -1)
        other.keyframes[kf.id] = kf
    for p in pt_ids:
        mp = src.points[p]
        mp.id, mp.first_kf = p + off_p, mp.first_kf + off_k
        mp.observations = {k + off_k: v for k, v in mp.observations.items()}
        other.points[mp.id] = mp
    other._next_kf, other._next_pt = off_k + a._next_kf, off_p + a._next_pt
    merged = copy.deepcopy(a)
    merged.absorb(other, T)
    assert not other.keyframes and not other.points
    assert len(merged.keyframes) == 2 * len(kf_ids) and len(merged.points) == 2 * len(pt_ids)
    k0, p0 = kf_ids[-1], pt_ids[7]
    np.testing.assert_allclose(merged.keyframes[k0 + off_k].T_world_cam, T @ a.keyframes[k0].T_world_cam, atol=1e-12)
    np.testing.assert_allclose(merged.points[p0 + off_p].xyz, T[:3, :3] @ a.points[p0].xyz + T[:3, 3], atol=1e-12)
    assert merged._next_kf == 2 * a._next_kf and merged.successor()._next_pt == 2 * a._next_pt


def test_a_keyframe_of_a_moved_copy_is_located_with_the_known_transform(room_tracker):
    """A map seen again in another frame (x' = T x): the located pose gives T back to 1 mm / 0.1 deg."""
    st = room_tracker
    atlas = Atlas(st.cfg.atlas, st.cam, st.stereo_cam, st.cfg.tracking, st.cfg.backend, make_place_descriptor("bow"))
    atlas.archive(0, st.map)
    T_new_old = make_T(_rot_z(30.0), np.array([1.0, 0.4, -0.3]))
    kf = st.map.keyframes[max(st.map.keyframes)]
    T_kf_new = T_new_old @ kf.T_world_cam  # the same keyframe as a new map would hold it
    hit = atlas.locate(kf.features, kf.ur, atlas.describe(kf.features))
    assert hit is not None
    map_id, cand, res = hit
    assert map_id == 0 and res.n_inliers >= st.cfg.atlas.merge_min_inliers
    T_old_new = res.T_world_cam @ inv_T(T_kf_new)
    D = T_old_new @ T_new_old  # identity when recovered
    assert np.linalg.norm(D[:3, 3]) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.1


def test_a_scaled_moved_copy_gives_the_similarity_back(room_tracker):
    """Monocular maps have a unit of their own: a copy of the map at half scale, rotated and moved, is located
    in the original and the similarity between them recovered (scale to 0.1 %, 1 mm, 0.1 deg)."""
    st = room_tracker
    atlas = Atlas(st.cfg.atlas, st.cam, st.stereo_cam, st.cfg.tracking, st.cfg.backend, make_place_descriptor("bow"))
    atlas.archive(0, st.map)
    s_true, R_true, t_true = 0.5, _rot_z(-40.0), np.array([0.3, -1.2, 0.5])  # x_new = s R x_old + t
    new = copy.deepcopy(st.map)
    for kf in new.keyframes.values():
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_true @ kf.T_world_cam[:3, :3], s_true * (R_true @ kf.T_world_cam[:3, 3]) + t_true
        kf.T_world_cam = T
    for mp in new.points.values():
        mp.xyz = s_true * (R_true @ mp.xyz) + t_true
    kf = new.keyframes[max(new.keyframes)]
    nan = np.full(len(kf.features), np.nan)  # monocular: no depth in the measurements
    hit = atlas.locate(kf.features, nan, atlas.describe(kf.features))
    assert hit is not None
    _, _, res = hit
    scale = atlas.scale(st.map, new, kf, res)
    assert scale == pytest.approx(1 / s_true, rel=1e-3)
    T = atlas.old_from_new(kf.T_world_cam, res.T_world_cam, scale)  # x_old = scale R x_new + t
    assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3] @ R_true) - 1) / 2, -1, 1))) < 0.1
    merged = Map()
    merged.absorb(new, T, scale)  # every keyframe and point lands on its original
    for k, f in st.map.keyframes.items():
        assert np.linalg.norm(merged.keyframes[k].T_world_cam[:3, 3] - f.T_world_cam[:3, 3]) < 1e-3
    for p, mp in st.map.points.items():
        np.testing.assert_allclose(merged.points[p].xyz, mp.xyz, atol=3e-3)


def test_matching_within_nodes_locates_a_frame_as_every_pair_does(room_tracker):
    """``locate`` matches the frame once against the points of all its candidates, within coarse vocabulary
    nodes (``match_nodes``) or over every pair (0): a later frame of the same map is found by both, at the same
    pose to 1 mm / 0.1 deg, with as many inliers to 5 %; and again the same result (the map's index is kept)."""
    st = room_tracker
    seq = SyntheticSequence(SyntheticConfig(n_frames=36, **SMALL))
    frame = list(seq)[35]  # 6 frames past the map's last one: not a keyframe of it
    feats = st.extractor.detect(frame.image, st.cam)
    ur = stereo_ur(feats.uv, st.front_end.depth(frame, feats, None), st.cam.fx, st.baseline)
    hits = {}
    for nodes in (16, 0):
        cfg = replace(st.cfg.atlas, match_nodes=nodes)
        atlas = Atlas(cfg, st.cam, st.stereo_cam, st.cfg.tracking, st.cfg.backend, make_place_descriptor("bow"))
        atlas.archive(0, st.map)
        vec = atlas.describe(feats)
        hits[nodes] = atlas.locate(feats, ur, vec, method="relocalised")
        again = atlas.locate(feats, ur, vec, method="relocalised")
        assert hits[nodes] is not None and again is not None
        np.testing.assert_array_equal(again[2].T_world_cam, hits[nodes][2].T_world_cam)
    (m16, _, r16), (m0, _, r0) = hits[16], hits[0]
    assert m16 == m0 == 0
    D = inv_T(r0.T_world_cam) @ r16.T_world_cam
    assert np.linalg.norm(D[:3, 3]) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.1
    assert abs(r16.n_inliers - r0.n_inliers) <= 0.05 * r0.n_inliers


def test_no_candidate_in_an_unrelated_map(room_tracker):
    """A keyframe of another scene (the street) is not located in the room's map: no merge on weak evidence."""
    st = room_tracker
    atlas = Atlas(st.cfg.atlas, st.cam, st.stereo_cam, st.cfg.tracking, st.cfg.backend, make_place_descriptor("bow"))
    atlas.archive(0, st.map)
    street = SyntheticSequence(SyntheticConfig(scene="street", n_frames=2, **SMALL))
    other = SlamTracker(street.calibration, "rgbd", SlamConfig())
    other.track(next(iter(street)))
    kf = other.map.keyframes[0]
    assert atlas.locate(kf.features, kf.ur, atlas.describe(kf.features)) is None


def test_a_merge_needs_consecutive_keyframes_that_agree():
    """``Atlas.vote``: the second keyframe in a row that finds the same map with a transform within 5 deg / 0.2 m
    of the first's allows the merge; another map, a turned or (metric maps only) shifted transform, starts over."""
    from vslam.tracking.atlas import AtlasConfig

    atlas = Atlas(AtlasConfig(), None, None, None, None)
    T = make_T(_rot_z(30.0), np.array([1.0, 2.0, 0.0]))
    near = make_T(_rot_z(33.0), np.array([1.1, 2.0, 0.0]))
    assert not atlas.vote(0, T, metric=True) and atlas.vote(0, near, metric=True)
    atlas.votes = []
    assert not atlas.vote(0, T, True) and not atlas.vote(1, T, True) and atlas.vote(1, near, True)  # other map
    atlas.votes = []
    assert not atlas.vote(0, T, True) and not atlas.vote(0, make_T(_rot_z(40.0), T[:3, 3]), True)  # turned 10 deg
    atlas.votes = []
    far = make_T(_rot_z(30.0), np.array([1.5, 2.0, 0.0]))
    assert not atlas.vote(0, T, True) and not atlas.vote(0, far, True)  # 0.5 m apart
    atlas.votes = []
    assert not atlas.vote(0, T, False) and atlas.vote(0, far, False)  # monocular: units differ, rotation only


def _check_multi_map_outputs(res, out) -> None:
    """A run that ends in several maps leads with the whole picture everywhere a reader looks: the printed summary
    (maps, posed of read frames, each map's ATE, then the largest map's number labelled as such), metrics.json
    (``run`` with the posed fraction and every map, ``maps`` with each map's evaluation) and report.html."""
    import io
    import json
    from contextlib import redirect_stdout

    from vslam.cli.app import _summary

    assert res.scored_map == 0 and res.n_frames == 70
    text = io.StringIO()
    with redirect_stdout(text):
        _summary(res, out)
    lines = text.getvalue().splitlines()
    assert lines[0].startswith("frames: 70 read, 70 posed (70 tracked); ")
    assert lines[1] == "maps: 1 new after tracking losses, 0 merged into older ones, 0 taken up again by relocalisation; 2 at the end"
    assert lines[3] == "2 maps, never merged; posed 70 of 70 frames; each map aligned on its own:"
    assert lines[4].startswith("  map 0: 40 poses, ATE 0.00") and lines[5].startswith("  map 1: 30 poses, ATE 0.00")
    assert lines[6].startswith("largest map only (map 0, 40 of 70 frames): ATE 0.00") and lines[6].endswith("40 poses")
    metrics = json.loads((out / "report" / "metrics.json").read_text())
    run = metrics["run"]
    assert (run["frames"], run["posed"], run["posed_fraction"], run["scored_map"]) == (70, 70, 1.0, 0)
    assert (run["new_maps"], run["merges"], run["map_switches"]) == (1, 0, 0)
    assert [(m["map"], m["poses"]) for m in run["maps"]] == [(0, 40), (1, 30)]
    for m in run["maps"]:
        assert m["ate_rmse"] == pytest.approx(metrics["maps"][str(m["map"])]["ate"]["translation_m"]["rmse"])
        assert m["align"] == "se3"
    assert metrics["ate"]["translation_m"]["rmse"] == run["maps"][0]["ate_rmse"]  # the headline: the largest map
    html = (out / "report" / "report.html").read_text()
    assert "Maps (never merged; each aligned on its own)" in html and "Summary: largest map (map 0, 40 of 70 frames)" in html
    assert html.count("aligned to the ground truth on its own") == 2  # a trajectory plot per map


def test_a_gap_starts_a_new_map_at_once_and_maps_are_scored_apart(tmp_path):
    """RGB-D, 2 s cut out of a path that does not come back: the frame after the gap starts map 1 (no frame
    predicted), the two maps are never merged, and each is evaluated in its own frame."""
    seq = select_frames(SyntheticSequence(SyntheticConfig(n_frames=130, **SMALL)), drop=((40, 99),))
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic"}, "output": {"report": True},
                                     "slam": {"save_map": True}})
    res, rows = _run(seq, cfg, tmp_path)
    by_index = {int(r["index"]): r for r in rows}
    assert by_index[100]["status"] == "new_map" and by_index[100]["map_id"] == "1"
    assert {r["status"] for r in rows} <= {"tracked", "new_map"}
    assert [int(r["map_id"]) for r in rows] == [0] * 40 + [1] * 30
    assert sorted(res.map_evals) == [0, 1]
    for e in res.map_evals.values():  # each map on its own is as good as an unbroken run (~3 mm)
        assert e.ate.translation.rmse < 0.0045  # 1.5x
    assert (tmp_path / "report" / "maps.json").exists()
    assert len(read_trajectory(tmp_path / "trajectory_final.tum.txt")) == 70
    _check_multi_map_outputs(res, tmp_path)
    # the map file holds both maps, each whole, and a run loading it has the old one to merge into
    loaded = load_map(tmp_path / "map.vslam.npz")
    assert loaded.current == 1 and sorted(loaded.others) == [0] and loaded.header["maps"] == [0, 1]
    m0, db0 = loaded.others[0]
    assert sorted(k.frame_index for k in loaded.map.keyframes.values())[0] == 100
    assert max(k.frame_index for k in m0.keyframes.values()) < 40 and len(db0) == len(m0.keyframes)
    assert not set(m0.points) & set(loaded.map.points)
    for m in (m0, loaded.map):
        for p in m.points.values():
            assert set(p.observations) <= set(m.keyframes)
    again = SlamTracker(seq.calibration, "rgbd", SlamConfig(load_map=str(tmp_path / "map.vslam.npz")))
    assert again.map_id == 1 and sorted(again.atlas.maps) == [0] and len(again.atlas.dbs[0]) == len(m0.keyframes)
    assert again.atlas.new_id() == 2


def test_a_camera_back_after_a_gap_is_relocalised_in_its_map_before_any_new_map(tmp_path):
    """The loop route with 175 frames cut out: the camera comes back 0.24 m / 18 deg from where it started. The
    frame after the gap is searched as a wide baseline (looser ratio test against the newest keyframes) and
    continues map 0: no new map, one trajectory."""
    seq = select_frames(SyntheticSequence(SyntheticConfig(n_frames=270, loop=True, **SMALL)), drop=((40, 215),))
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic"}, "output": {"report": False}})
    res, rows = _run(seq, cfg, tmp_path)
    by_index = {int(r["index"]): r for r in rows}
    assert by_index[216]["status"] == "relocalised" and by_index[216]["map_id"] == "0"
    assert {r["map_id"] for r in rows} == {"0"} and res.recovery == {"new_maps": 0, "merges": 0, "map_switches": 0}
    assert res.eval.ate.translation.rmse < 0.0106  # measured 0.0070 m; bound 1.5x


def test_a_camera_back_in_an_archived_map_takes_it_up_again(tmp_path):
    """Loop route, two stretches cut out: after the first the camera is elsewhere (map 1 starts at once), after
    the second it is back near the start, which map 1 never saw: the frame is found in archived map 0 (place
    retrieval + PnP), map 0 continues and map 1 is archived. Ids stay unique across the maps."""
    seq = select_frames(SyntheticSequence(SyntheticConfig(n_frames=270, loop=True, **SMALL)),
                        drop=((40, 119), (150, 225)))
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic"}, "output": {"report": False},
                                     "slam": {"save_map": True}})
    res, rows = _run(seq, cfg, tmp_path)
    by_index = {int(r["index"]): r for r in rows}
    assert by_index[120]["status"] == "new_map" and by_index[120]["map_id"] == "1"
    assert by_index[226]["status"] == "relocalised" and by_index[226]["map_id"] == "0"
    assert {by_index[i]["map_id"] for i in range(226, 270)} == {"0"}
    assert res.recovery == {"new_maps": 1, "merges": 0, "map_switches": 1}
    for e in res.map_evals.values():  # each map as good as an unbroken run (measured 0.0073 / 0.0077 m)
        assert e.ate.translation.rmse < 0.011
    loaded = load_map(tmp_path / "map.vslam.npz")
    assert loaded.current == 0 and sorted(loaded.others) == [1]
    m1, _ = loaded.others[1]
    assert not set(m1.keyframes) & set(loaded.map.keyframes) and not set(m1.points) & set(loaded.map.points)
    assert max(loaded.map.keyframes) > max(m1.keyframes)  # map 0's new keyframes continue after map 1's ids


def test_at_a_low_frame_rate_one_unmeasured_frame_does_not_start_a_map():
    """3 Hz (every 10th frame), one frame showing another room (its image only: depth and pose unchanged): with
    ``atlas.min_lost_frames`` 2 it is predicted and the next frame is tracked in map 0 again; with 1 (a new map
    at the first unmeasured frame) it starts map 1, and the next frame, found in archived map 0, takes it up again."""
    from vslam.tracking.atlas import AtlasConfig

    one = SyntheticSequence(SyntheticConfig(n_frames=130, **SMALL))
    other = SyntheticSequence(SyntheticConfig(n_frames=130, second_room=1, **SMALL))
    runs = {}
    for lost_frames in (2, 1):
        st = SlamTracker(one.calibration, "rgbd", SlamConfig(atlas=AtlasConfig(min_lost_frames=lost_frames)))
        seen = []
        for i in range(0, 130, 10):
            f = one.frame(i)
            if i == 100:
                f.image = other.frame(i).image
            e = st.track(f)
            seen.append((e.status_name, e.map_id))
        runs[lost_frames] = (seen, st.recovery_stats())
    seen, rec = runs[2]
    assert seen[:10] == [("tracked", 0)] * 10 and seen[10] == ("predicted", 0) and seen[11:] == [("tracked", 0)] * 2
    assert rec == {"new_maps": 0, "merges": 0, "map_switches": 0}
    seen, rec = runs[1]
    assert seen[10] == ("new_map", 1) and seen[11] == ("relocalised", 0) and seen[12] == ("tracked", 0)
    assert rec == {"new_maps": 1, "merges": 0, "map_switches": 1}


def test_a_new_map_that_meets_the_old_one_is_merged(tmp_path):
    """The loop route with 175 frames cut out, without the wide-baseline search (``tracking.wide_gap_s`` out of
    reach) and without relocalisation into archived maps: the camera, back 0.24 m / 18 deg from where it
    started, is not tracked against the old map at once; a new map starts and is merged into map 0 at a later
    keyframe, and the final trajectory is one frame (ATE over every frame as low as the unbroken run's)."""
    seq = select_frames(SyntheticSequence(SyntheticConfig(n_frames=270, loop=True, **SMALL)), drop=((40, 215),))
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic"}, "output": {"report": False},
                                     "slam": {"tracking": {"wide_gap_s": 1e9}, "atlas": {"relocalise": False}}})
    res, rows = _run(seq, cfg, tmp_path)
    by_index = {int(r["index"]): r for r in rows}
    assert by_index[216]["status"] == "new_map" and by_index[216]["map_id"] == "1"
    assert by_index[269]["map_id"] == "0"  # after the merge the frames are in map 0 again
    assert by_index[216]["final_map_id"] == "0"  # stats.csv: where the frames of map 1 ended
    assert {r["final_map_id"] for r in rows} == {"0"} and res.recovery["merges"] == 1
    assert set(res.map_ids.tolist()) == {0} and not res.map_evals
    assert res.eval.ate.translation.rmse < 0.0137  # one frame for all 94 poses (measured 0.0091 m; bound 1.5x)
    final = read_trajectory(tmp_path / "trajectory_final.tum.txt")
    assert len(final) == 94


def test_lost_frames_have_no_pose(tmp_path):
    """A blackout longer than the 1 s bridge: predicted for 1 s, then "lost" (no pose: in stats.csv, not in the
    trajectory) until a frame can start a map."""
    scfg = SyntheticConfig(n_frames=110, blackouts=((30, 60),), **SMALL)
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic"}, "output": {"report": False}})
    res, rows = _run(SyntheticSequence(scfg), cfg, tmp_path)
    status = {int(r["index"]): r["status"] for r in rows}
    assert {status[i] for i in range(30, 60)} == {"predicted"}  # within the bridge
    assert {status[i] for i in range(61, 90)} == {"lost"}
    assert status[90] in ("tracked", "new_map")
    stamps = read_trajectory(tmp_path / "trajectory.tum.txt").timestamps
    assert len(stamps) == len(rows) - 29 - (status[60] == "lost")
    assert len(res.trajectory) == len(stamps)


def test_tracking_states_on_a_blur_and_a_blackout():
    """initialising -> tracking; blurred frames: lost (predicted), then relocalising (too few corners to start a
    map: the old one is still tried) until the sharp frames are tracked again; a black stretch the same, its
    frames past the 1 s bridge without a pose; the first frame after it (1.2 s further on, not found in the old
    map) starts map 1."""
    scfg = SyntheticConfig(n_frames=70, blurs=((10, 6),), blur_sigma=8.0, blackouts=((25, 36),), **SMALL)
    seq = SyntheticSequence(scfg)
    st = SlamTracker(seq.calibration, "rgbd", SlamConfig())
    assert st.state == "initialising"
    states, status = [], []
    for f in seq:
        est = st.track(f)
        states.append(st.state)
        status.append(est.status_name)
    assert states[:10] == ["tracking"] * 10
    assert states[10:12] == ["lost"] * 2 and set(states[12:16]) == {"relocalising"}  # 0.1 s: 3 frames at 30 Hz
    assert states[16:25] == ["tracking"] * 9
    assert states[25:27] == ["lost"] * 2 and set(states[27:61]) == {"relocalising"}
    assert status[25:54] == ["predicted"] * 29 and set(status[56:61]) == {"lost"}  # the 1 s bridge
    assert states[61:] == ["tracking"] * 9 and status[61] == "new_map" and st.map_id == 1  # 1.2 s on: a new map


@pytest.mark.slow
def test_stereo_inertial_blackout_past_the_bridge_starts_a_new_map(tmp_path):
    """Stereo-inertial, a 2 s blackout: the IMU bridges 1 s (predicted), then no pose until the first frame with
    images, which starts map 1 from the IMU's pose, and the IMU chain restarts on it (IMU factors again:
    stats.csv imu "used"). Before the Atlas ran with an IMU, every frame after the blackout was "predicted"."""
    scfg = SyntheticConfig(n_frames=150, scene="room", n_movers=0, width=320, height=240, fx=262.5, fy=262.5,
                           blackouts=((60, 60),))
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "synthetic", "sensor": "stereo"}, "output": {"report": False},
                                     "slam": {"inertial": {"enabled": True}}})
    res, rows = _run(SyntheticSequence(scfg, sensor="stereo"), cfg, tmp_path)
    status = {int(r["index"]): r["status"] for r in rows}
    assert {status[i] for i in range(60, 90)} == {"predicted"}
    assert {status[i] for i in range(91, 120)} == {"lost"}
    assert status[120] == "new_map" and {status[i] for i in range(121, 150)} == {"tracked"}
    assert rows[-1]["map_id"] == "1" and rows[-1]["imu"] == "used"
    for e in res.map_evals.values():  # measured 0.025 (with the predicted frames) and 0.003 m
        assert e.ate.translation.rmse < 0.035


def test_yaw_only_keeps_the_turn_about_gravity_and_the_keyframe_centre():
    yaw, tilt = _rot_z(30.0), np.array([[1, 0, 0], [0, np.cos(0.02), -np.sin(0.02)], [0, np.sin(0.02), np.cos(0.02)]])
    T_old_new = make_T(yaw @ tilt, np.array([1.0, -2.0, 0.5]))
    T_new = make_T(_rot_z(-70.0), np.array([0.3, 0.4, 1.2]))
    T = Atlas.yaw_only(T_old_new, T_new)
    np.testing.assert_allclose(T[:3, :3], yaw, atol=1e-3)  # the 1.1 degree roll is gone, the 30 degree yaw kept
    np.testing.assert_allclose(T[:3, :3] @ T_new[:3, 3] + T[:3, 3], (T_old_new @ T_new)[:3, 3], atol=1e-12)
    np.testing.assert_allclose(Atlas.yaw_only(make_T(yaw, [1, 2, 3]), T_new), make_T(yaw, [1, 2, 3]), atol=1e-12)
