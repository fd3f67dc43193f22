"""Line landmarks follow their keyframe when a loop correction (rigid or similarity) or an inertial
rescale moves the map."""

from __future__ import annotations

import numpy as np

from vslam.backend.pose_graph import sim_matrix, sim_parts
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import make_T, so3_exp
from vslam.mapping.line_map import LineMap, LineSlam, moved_line

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
K_L = pl.line_projection_matrix(500.0, 500.0, 320.0, 240.0)


def _pose(rng, t_scale=2.0):
    return make_T(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, t_scale, 3))


def _segment_seen_from(T, rng):
    """A 3-D segment 3-6 m in front of camera T -> (L (6,), ends (2,3), its image segment (4,))."""
    c = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(3, 6)])
    d = rng.normal(size=3)
    ends_c = np.stack([c - 0.5 * d, c + 0.5 * d])
    ends = ends_c @ T[:3, :3].T + T[:3, 3]
    uv = ends_c @ K.T
    seg = (uv[:, :2] / uv[:, 2:]).reshape(4)
    return pl.normalize(pl.from_points(ends[0], ends[1])), ends, seg


def _distances(L, T, seg):
    return pl.segment_distances(seg[None], pl.project(L[None], T, K_L))[0]


def test_moved_line_keeps_its_image_in_the_moved_keyframe():
    rng = np.random.default_rng(0)
    for scale in (1.0, 0.7, 1.4):  # rigid and similarity corrections
        T0 = _pose(rng)
        L, ends, seg = _segment_seen_from(T0, rng)
        S_after = sim_matrix(_pose(rng), scale)
        D = S_after @ np.linalg.inv(sim_matrix(T0))  # what the loop closer hands to ``follow``
        L2, ends2 = moved_line(L, ends, D)
        R, t, _ = sim_parts(S_after)
        T1 = make_T(R, t)  # the keyframe's corrected pose
        np.testing.assert_allclose(_distances(L2, T1, seg), 0.0, atol=1e-7)
        assert abs(pl.constraint(L2)) < 1e-12 and abs(np.linalg.norm(L2[3:]) - 1.0) < 1e-12
        np.testing.assert_allclose(ends2, ends @ D[:3, :3].T + D[:3, 3], atol=1e-12)
        assert (L2[3:] @ (ends2[1] - ends2[0])) > 0  # orientation kept


def test_follow_moves_each_line_with_its_first_keyframe_and_transform_moves_all():
    rng = np.random.default_rng(1)
    ls = LineSlam.__new__(LineSlam)  # only the line map is needed here
    ls.lmap = LineMap()
    poses = {0: _pose(rng), 1: _pose(rng)}
    segs = {}
    for kf in (0, 1):
        ls.lmap.kf_feats[kf] = type("F", (), {"desc": np.zeros((2, 4), np.float32)})()
        ls.lmap.kf_ids[kf] = np.full(2, -1, np.int64)
    for kf in (0, 1):
        L, ends, seg = _segment_seen_from(poses[kf], rng)
        ml = ls.lmap.add_line(L, ends, kf, 0)
        segs[ml.id] = (kf, seg)
    delta = {0: sim_matrix(_pose(rng)), 1: sim_matrix(_pose(rng))}
    new_poses = {k: delta[k] @ poses[k] for k in poses}
    ls.follow(delta)
    for lid, (kf, seg) in segs.items():
        np.testing.assert_allclose(_distances(ls.lmap.lines[lid].L, new_poses[kf], seg), 0.0, atol=1e-7)
    # the whole map into a new world at another scale (monocular inertial initialisation)
    ls.map = type("M", (), {"keyframes": poses})()
    T, s = _pose(rng), 2.5
    before = {lid: ml.ends.copy() for lid, ml in ls.lmap.lines.items()}
    ls.transform(T, s)
    for lid, ml in ls.lmap.lines.items():
        np.testing.assert_allclose(ml.ends, (s * before[lid]) @ T[:3, :3].T + T[:3, 3], atol=1e-12)


def test_depth_fit_recovers_a_line_on_a_surface_and_rejects_one_across_a_depth_edge():
    """RGB-D line creation, batched over segments: a segment drawn on a tilted plane gives that 3-D line
    (in the world, under the keyframe pose); one crossing from the plane to a far background, and one with
    no depth, give none."""
    from vslam.data.types import PinholeCamera
    from vslam.features.lines import LineConfig

    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    ls = LineSlam.__new__(LineSlam)
    ls.cam, ls.cfg = cam, LineConfig()
    # plane z = 3 + 0.5 x (camera frame) on the left half, background at 8 m on the right; no depth at the top
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    xn = (u - 320.0) / 500.0
    depth = np.where(u < 400, 3.0 / (1.0 - 0.5 * xn), 8.0).astype(np.float32)
    depth[:60] = np.nan
    T = make_T(so3_exp(np.array([0.1, -0.2, 0.05])), np.array([1.0, 2.0, 0.5]))

    def seg_of(p, q):
        return np.array([*(K @ p)[:2] / p[2], *(K @ q)[:2] / q[2]])

    on = [np.array([x, y, 3.0 + 0.5 * x]) for x, y in ((-0.6, -0.3), (0.1, 0.4))]  # both ends on the plane
    segs = np.stack([seg_of(*on), np.array([200.0, 300.0, 600.0, 300.0]), np.array([100.0, 20.0, 300.0, 40.0])])
    ok, L, ends = ls.fit_from_depth(segs, segs, depth, T)
    assert ok.tolist() == [True, False, False]
    truth = pl.transform(pl.normalize(pl.from_points(on[0], on[1])), T)
    s = np.sign(truth[3:] @ L[0][3:])
    np.testing.assert_allclose(s * pl.normalize(L[0]), truth, atol=2e-2)  # depth sampled at rounded pixels
    np.testing.assert_allclose(ends[0], np.stack(on) @ T[:3, :3].T + T[:3, 3], atol=3e-2)
    assert np.isnan(L[1:]).all()


def test_depth_lines_keep_creases_and_drop_occluding_contours():
    """``reject_contours``: a wall-floor crease (two surfaces meeting at the segment) makes a line; the outline
    of a near object in front of a far wall (a silhouette: no fixed 3-D line) does not -- it does with the check
    off, as a line on the near side."""
    import dataclasses

    from vslam.data.types import PinholeCamera
    from vslam.features.lines import LineConfig

    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    yn = (v - 240.0) / 500.0
    # crease: a wall at z = 4 above row 315, below it the floor y = 0.6 (camera y down), meeting the wall there
    crease = np.where(v < 315, 4.0, 0.6 / np.maximum(yn, 1e-6))
    # contour: a box at 1.5 m covering columns 200-399 in front of a wall at 4 m
    contour = np.where((u >= 200) & (u < 400) & (v >= 100) & (v < 400), 1.5, 4.0)
    T = np.eye(4)
    seg = np.array([[250.0, 315.0, 450.0, 315.0]])  # along the crease / ...
    edge = np.array([[400.0, 150.0, 400.0, 350.0]])  # ... along the box's right outline
    for on in (True, False):
        ls = LineSlam.__new__(LineSlam)
        ls.cam, ls.cfg = cam, dataclasses.replace(LineConfig(), reject_contours=on)
        ok_c, _, ends_c = ls.fit_from_depth(seg, seg, crease.astype(np.float32), T)
        assert ok_c.tolist() == [True]
        np.testing.assert_allclose(ends_c[0][:, 2], 3.9, atol=0.11)  # the nearer side, the floor 2 px down
        ok_e, L_e, ends = ls.fit_from_depth(edge, edge, contour.astype(np.float32), T)
        assert ok_e.tolist() == [not on]
        if not on:  # the near side's depth: the silhouette placed on the box
            np.testing.assert_allclose(ends[0][:, 2], 1.5, atol=1e-6)


def test_end_point_depths_are_read_off_each_side_extrapolated_to_the_segment():
    """RGB-D line observations measure their end points' depth: on a steeply tilted plane the nearer side
    2 px off the segment is ~5 mm nearer at 3 m than the segment (the creation fit's bias); each side
    extrapolated to the segment (and the two averaged) reads the plane's depth there, so the measured inverse
    depths equal the truth; a crease reads where its two surfaces meet. A frame without a depth map gets none."""
    from vslam.data.types import PinholeCamera
    from vslam.features.lines import LineConfig, LineFeatures

    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    ls = LineSlam.__new__(LineSlam)
    ls.cam, ls.cfg, ls.K_L, ls.depth_weight = cam, LineConfig(), K_L, 1.0
    ls.extractor = None
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    xn, yn = (u - 320.0) / 500.0, (v - 240.0) / 500.0
    plane = 3.0 / (1.0 - 0.6 * xn)  # z = 3 + 0.6 x: a wall seen at a slant
    crease = np.where(v < 315, 4.0, 0.6 / np.maximum(yn, 1e-6))  # wall at 4 m meeting the floor at row 315
    on = np.array([[-0.5, -0.4, 3.0 - 0.3], [0.2, 0.5, 3.0 + 0.12]])  # a vertical-ish segment on the plane
    uv = on @ K.T
    seg = (uv[:, :2] / uv[:, 2:]).reshape(1, 4)
    lf = LineFeatures(seg, seg, np.zeros((1, 8), np.float32), np.array([100.0]))
    rho = ls.end_inverse_depths(lf, plane.astype(np.float32))
    np.testing.assert_allclose(rho[0], 1.0 / on[:, 2], rtol=2e-3)
    _, _, near = ls.fit_from_depth(seg, seg, plane.astype(np.float32), np.eye(4))  # creation: the nearer side
    err_near, err_ex = np.abs(near[0][:, 2] - on[:, 2]), np.abs(1.0 / rho[0] - on[:, 2])
    assert err_near.min() > 0.004 and err_ex.max() < 0.25 * err_near.min(), (err_near, err_ex)
    cs = np.array([[250.0, 315.0, 450.0, 315.0]])
    rho_c = ls.end_inverse_depths(LineFeatures(cs, cs, np.zeros((1, 8), np.float32), np.array([200.0])), crease.astype(np.float32))
    np.testing.assert_allclose(rho_c[0], 1.0 / 4.0, rtol=5e-3)


def test_stereo_end_point_depths_from_the_right_images_matching_segment():
    """Stereo line observations measure their end points' depth by intersecting the planes of a segment and
    its match in the right image: exact for noiseless segments; none for a segment along the epipolar lines
    (rectified rig: horizontal), whose two planes coincide."""
    from vslam.data.types import Calibration, PinholeCamera
    from vslam.backend.ba import StereoCamera
    from vslam.features.lines import LineConfig, LineFeatures

    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    T_b1 = np.eye(4)
    T_b1[0, 3] = 0.1  # right camera 10 cm along x
    calib = Calibration(cam0=cam, cam1=cam, T_body_cam1=T_b1)
    ls = LineSlam(None, cam, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.1), "stereo", LineConfig(), None, calib)
    ends = np.array([[[-0.6, -0.5, 3.0], [-0.4, 0.6, 3.5]],   # steep
                     [[0.3, -0.4, 4.0], [0.9, 0.5, 2.5]],     # steep, receding
                     [[-0.8, 0.3, 3.0], [0.8, 0.31, 3.0]]])   # horizontal: along the epipolar lines

    def segs_in(shift):
        uv = (ends - [shift, 0, 0]) @ K.T
        return (uv[..., :2] / uv[..., 2:]).reshape(-1, 4)

    rng = np.random.default_rng(0)
    desc = rng.normal(size=(3, 8)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    left, right = segs_in(0.0), segs_in(0.1)
    lf = LineFeatures(left, left, desc, np.hypot(left[:, 2] - left[:, 0], left[:, 3] - left[:, 1]))
    perm = [2, 0, 1]  # the right image lists them in another order
    rf = LineFeatures(right[perm], right[perm], desc[perm], lf.length[perm])
    rho = ls.stereo_inverse_depths(lf, rf)
    np.testing.assert_allclose(rho[:2], 1.0 / ends[:2, :, 2], rtol=1e-9)
    assert np.isnan(rho[2]).all()


def test_stereo_keyframe_creates_lines_from_the_rigs_end_point_depths():
    """Stereo lines come from one keyframe, as RGB-D ones from the depth map: the rig's end-point depths place
    the segment in the world (exact for noiseless segments); no line where an end point has no depth or too
    small a disparity (``rig_min_disparity_px``)."""
    from vslam.backend.ba import StereoCamera
    from vslam.data.types import Calibration, PinholeCamera
    from vslam.features.lines import LineConfig, LineFeatures

    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    T_b1 = np.eye(4)
    T_b1[0, 3] = 0.1
    calib = Calibration(cam0=cam, cam1=cam, T_body_cam1=T_b1)
    ls = LineSlam(None, cam, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.1), "stereo", LineConfig(create="depth"), None, calib)
    auto = LineSlam(None, cam, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.1), "stereo", LineConfig(), None, calib)
    assert auto.from_depth and auto.from_two_views  # "auto" with a measuring rig: the rig, then two views
    rng = np.random.default_rng(3)
    T = _pose(rng)
    ends_c = np.array([[[-0.6, -0.5, 3.0], [-0.4, 0.6, 3.5]],
                       [[0.3, -0.4, 4.0], [0.9, 0.5, 2.5]],
                       [[-0.8, 0.3, 3.0], [-0.7, 0.9, 3.0]],      # no depth at one end (unmatched there)
                       [[0.1, 0.2, 30.0], [0.3, 1.9, 30.0]]])     # 30 m: 1.7 px of disparity
    uv = ends_c @ K.T
    segs = (uv[..., :2] / uv[..., 2:]).reshape(-1, 4)
    rho = 1.0 / ends_c[..., 2]
    rho[2, 1] = np.nan
    lf = LineFeatures(segs, segs, np.zeros((4, 8), np.float32), np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]), rho)
    assert ls.add_keyframe(0, T, lf, None, None) == 2
    made = {ml.observations[0]: ml for ml in ls.lmap.lines.values()}
    assert set(made) == {0, 1}
    for i, ml in made.items():
        ends_w = ends_c[i] @ T[:3, :3].T + T[:3, 3]
        np.testing.assert_allclose(ml.ends, ends_w, atol=1e-9)
        np.testing.assert_allclose(np.abs(ml.L), np.abs(pl.normalize(pl.from_points(ends_w[0], ends_w[1]))), atol=1e-9)
        assert not ml.two_view
    mono = LineSlam(None, cam, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.0), "mono", LineConfig(), None, calib)
    assert not mono.from_depth and mono.from_two_views
