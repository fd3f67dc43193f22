"""Map bookkeeping: observations both ways, covisibility, fusion, culling; the keyframe rule."""

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.mapping.local_mapping import LocalMapper, MappingConfig
from vslam.mapping.map import Map
from vslam.tracking.tracker import TrackingConfig, need_keyframe


def _feats(n, seed=0):
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0, 300, size=(n, 2))
    return Features(uv, uv.copy(), rng.integers(0, 256, (n, 32), dtype=np.uint8), np.zeros(n, np.int64), np.ones(n))


def _map_with(n_kf=3, n_kp=40):
    m = Map()
    for k in range(n_kf):
        m.add_keyframe(k, float(k), np.eye(4), _feats(n_kp, k), np.full(n_kp, np.nan), np.full(n_kp, np.nan))
    return m


def test_apply_adjustment_keeps_depth_only_outliers_as_mono():
    m = _map_with(2)
    m.keyframes[1].ur[:] = 100.0
    a, b = m.add_point(np.zeros(3), 0, 1), m.add_point(np.ones(3), 0, 2)
    m.add_observation(a.id, 1, 3)
    m.add_observation(b.id, 1, 4)
    obs_kf, obs_pt = np.array([1, 1]), np.array([a.id, b.id])
    m.apply_adjustment({}, {}, np.array([False, False]), obs_kf, obs_pt, depth_only=np.array([True, False]))
    assert 1 in m.points[a.id].observations and np.isnan(m.keyframes[1].ur[3])  # kept, as mono
    assert 1 not in m.points[b.id].observations and m.keyframes[1].ur[4] == 100.0  # removed


def test_observations_are_kept_consistent():
    m = _map_with()
    p = m.add_point(np.zeros(3), 0, 5)
    m.add_observation(p.id, 1, 7)
    assert p.observations == {0: 5, 1: 7}
    assert m.keyframes[0].point_ids[5] == p.id and m.keyframes[1].point_ids[7] == p.id
    m.add_observation(p.id, 1, 8)  # re-observed at another keypoint of the same keyframe: moves
    assert m.keyframes[1].point_ids[7] == -1 and m.keyframes[1].point_ids[8] == p.id
    m.remove_observation(p.id, 0)
    assert m.keyframes[0].point_ids[5] == -1 and p.id in m.points
    m.remove_observation(p.id, 1)  # last observation gone: the point goes too
    assert p.id not in m.points and (m.keyframes[1].point_ids == -1).all()
    ids = [m.add_point(np.zeros(3), 2, i).id for i in range(3)]
    assert ids == sorted(ids) and ids[0] > p.id  # ids only increase


def test_covisibility_counts_and_local_map():
    m = _map_with(4)
    for i in range(20):  # kf0-kf1 share 20, kf0-kf2 share 10, kf3 shares nothing
        p = m.add_point(np.zeros(3), 0, i)
        m.add_observation(p.id, 1, i)
        if i < 10:
            m.add_observation(p.id, 2, i)
    assert m.covisibility(0) == {1: 20, 2: 10}
    assert m.covisibility(3) == {}
    assert m.covisible_keyframes(0, min_shared=15) == [1]
    assert m.covisible_keyframes(0, min_shared=1) == [1, 2]
    kfs, pts = m.local_map(2, min_shared=5)
    assert kfs == [2, 1, 0] and len(pts) == 20  # ties (10 and 10): newest first
    # remembered while the map is unchanged; a caller cannot change the remembered copy
    kfs.append(99)
    kfs2, pts2 = m.local_map(2, min_shared=5)
    assert kfs2 == [2, 1, 0] and pts2 is pts and not pts2.flags.writeable
    assert m.local_map(2, min_shared=11)[0] == [2]  # other arguments: counted again
    for i in range(10, 20):  # kf2 now shares 20 with kf0 and kf1: any map change counts again
        m.add_observation(int(pts[i]), 2, i)
    assert m.local_map(2, min_shared=11)[0] == [2, 1, 0]
    m.remove_point(int(pts[0]))
    assert len(m.local_map(2, min_shared=11)[1]) == 19


def test_merge_points_moves_observations():
    m = _map_with()
    a = m.add_point(np.zeros(3), 0, 1)
    m.add_observation(a.id, 1, 1)
    b = m.add_point(np.ones(3), 2, 3)
    m.merge_points(a.id, b.id)
    assert b.id not in m.points and a.observations == {0: 1, 1: 1, 2: 3}
    assert m.keyframes[2].point_ids[3] == a.id


def test_culling_removes_weak_recent_points():
    m = _map_with(4)
    cam = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    mapper = LocalMapper(m, cam, StereoCamera(262.5, 262.5, 159.5, 119.5, 0.08), "rgbd", MappingConfig(), BackendConfig())
    rarely_found = m.add_point(np.zeros(3), 0, 0)
    rarely_found.n_visible, rarely_found.n_found = 10, 1
    lonely = m.add_point(np.zeros(3), 0, 1)  # seen by one keyframe only
    good = m.add_point(np.zeros(3), 0, 2)
    for k in (1, 2):
        m.add_observation(good.id, k, 2)
    young = m.add_point(np.zeros(3), 3, 3)
    mapper.recent = [rarely_found.id, lonely.id, good.id, young.id]
    mapper.cull(cur_kf=2)
    assert rarely_found.id not in m.points and lonely.id not in m.points
    assert good.id in m.points and young.id in m.points


def test_keyframe_decision():
    cfg = TrackingConfig()
    # plenty of tracked points relative to the reference: no keyframe
    assert not need_keyframe(300, 320, 5, 200, 10, "rgbd", cfg)
    # tracked points fell under kf_ratio of the reference's
    assert need_keyframe(200, 320, 5, 200, 10, "rgbd", cfg)
    # RGB-D: few close points tracked while many close keypoints are unmapped
    assert need_keyframe(300, 320, 5, 50, 200, "rgbd", cfg)
    assert not need_keyframe(300, 320, 5, 50, 200, "mono", cfg)
    # max frames elapsed
    assert need_keyframe(300, 320, cfg.kf_max_frames, 200, 10, "rgbd", cfg)
    # too few inliers to make a useful keyframe
    assert not need_keyframe(10, 320, 5, 5, 200, "rgbd", cfg)
    # monocular: kf_min_frames_mono holds a weak frame back, unless its inliers run out
    assert not need_keyframe(200, 320, 1, 0, 0, "mono", cfg)
    assert need_keyframe(200, 320, cfg.kf_min_frames_mono, 0, 0, "mono", cfg)
    assert need_keyframe(cfg.kf_min_inliers_mono - 1, 320, 1, 0, 0, "mono", cfg)


def test_local_ba_window_is_held_by_enough_fixed_points():
    # kf 0 (fixed) shares 5 points with the window; kf 1..3 share 150. Anchored by 5 points the window
    # floats (synthetic loop room: BA slid 3 keyframes 14 cm), so kf 1 joins the fixed set; kf 3 stays free.
    m = _map_with(4, 200)
    pts = []
    for i in range(5):
        p = m.add_point(np.zeros(3), 0, i)
        m.add_observation(p.id, 1, i)
        pts.append(p.id)
    for i in range(5, 155):
        p = m.add_point(np.zeros(3), 1, i)
        m.add_observation(p.id, 2, i)
        m.add_observation(p.id, 3, i)
        pts.append(p.id)
    cam = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    mapper = LocalMapper(m, cam, StereoCamera(300, 300, 150, 150, 0.08), "rgbd", MappingConfig(ba_min_anchor_points=100),
                         BackendConfig())
    window, fixed = [1, 2, 3], [0]
    mapper._anchor_window(3, window, fixed, np.array(pts))
    assert window == [2, 3] and fixed == [0, 1]
    window, fixed = [3], [0]
    mapper._anchor_window(3, window, fixed, np.array(pts))  # never the new keyframe
    assert window == [3] and fixed == [0]


def test_keyframe_when_few_inliers_rgbd():
    # fast forward motion: the reference keyframe's fresh points are not yet seen by 3 keyframes (ref_tracked
    # small) and nothing is close; the inlier floor still asks for a keyframe (RGB-D/stereo only)
    cfg = TrackingConfig()
    assert need_keyframe(60, 40, 5, 0, 0, "rgbd", cfg)
    assert not need_keyframe(60, 40, 5, 0, 0, "mono", cfg)
    assert not need_keyframe(cfg.kf_min_inliers + 50, 40, 5, 0, 0, "rgbd", cfg)


def test_batched_descriptor_update_equals_one_point_at_a_time():
    rng = np.random.default_rng(4)
    m = _map_with(n_kf=8, n_kp=60)
    for kf in m.keyframes.values():  # few distinct descriptors: many equal medians (ties break by first)
        kf.features.desc[:] = rng.integers(0, 256, (4, 32), dtype=np.uint8)[rng.integers(0, 4, 60)]
    ids = []
    for j in range(50):
        kfs = rng.choice(8, size=int(rng.integers(1, 8)), replace=False)
        p = m.add_point(np.zeros(3), int(kfs[0]), j)
        for k in kfs[1:]:
            m.add_observation(p.id, int(k), j)
        ids.append(p.id)
    one = Map()
    one.keyframes, one.points = m.keyframes, {i: type(m.points[i])(**vars(m.points[i])) for i in ids}
    for i in ids:
        one.points[i].observations = dict(m.points[i].observations)
        one.update_descriptor(i)
    m.update_descriptors(np.array(ids))
    assert sum(len(m.points[i].observations) >= 3 for i in ids) > 20
    for i in ids:
        np.testing.assert_array_equal(m.points[i].descriptor, one.points[i].descriptor)


def test_fusion_skips_points_merged_away_meanwhile():
    """Loop fusion hands one candidate list to several keyframes and merges as it goes: ids gone from the map
    are skipped, the rest still fuse."""
    m = _map_with(2)
    cam = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    mapper = LocalMapper(m, cam, StereoCamera(262.5, 262.5, 159.5, 119.5, 0.08), "rgbd", MappingConfig(), BackendConfig())
    target = m.keyframes[1]
    xyz = cam.backproject(target.features.uv[5:6], np.array([2.0]))[0]
    p = m.add_point(xyz, 0, 5)
    target.features.desc[5] = m.keyframes[0].features.desc[5]  # the same corner seen again
    gone = m.add_point(np.array([0.0, 0.0, 2.0]), 0, 6)
    m.remove_point(gone.id)
    assert mapper._fuse_into(target, np.array([gone.id, p.id])) == 1
    assert p.observations == {0: 5, 1: 5}


def test_add_points_equals_one_at_a_time():
    one, many = _map_with(2), _map_with(2)
    one.add_point(np.zeros(3), 1, 0)
    many.add_point(np.zeros(3), 1, 0)  # ids continue after existing points
    X, kps = np.arange(12.0).reshape(4, 3), np.array([7, 3, 9, 4])
    ids = [one.add_point(X[i], 0, int(k)).id for i, k in enumerate(kps)]
    assert many.add_points(X, 0, kps) == ids
    np.testing.assert_array_equal(many.keyframes[0].point_ids, one.keyframes[0].point_ids)
    for i in ids:
        a, b = one.points[i], many.points[i]
        assert (a.first_kf, a.observations, a.n_visible, a.n_found) == (b.first_kf, b.observations, b.n_visible, b.n_found)
        np.testing.assert_array_equal(a.xyz, b.xyz)
        np.testing.assert_array_equal(a.descriptor, b.descriptor)
    many.keyframes[0].features.desc[7] ^= 255  # the point keeps its own copy of the descriptor
    np.testing.assert_array_equal(many.points[ids[0]].descriptor, one.points[ids[0]].descriptor)
    assert many.revision == one.revision
    try:
        many.add_points(np.zeros((1, 3)), 0, np.array([7]))  # already a map point
    except ValueError as e:
        assert "keyframe 0" in str(e)
    else:
        raise AssertionError("expected a ValueError")
