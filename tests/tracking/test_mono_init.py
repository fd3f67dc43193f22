"""Monocular initialisation over a frame stream (``MonoInitializer``): which pair it takes (parallax, matches
kept, inlier ratio) and which model (homography on a plane, essential matrix on a general scene), on synthetic
views with exact descriptors."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.geometry.se3 import inv_T, make_T, so3_exp
from vslam.mapping.map import Map
from vslam.tracking.initializer import InitConfig, initialize_two_view
from vslam.tracking.mono_init import MonoInitializer

W, H = 640, 480
CAM = PinholeCamera(W, H, 500.0, 500.0, 320.0, 240.0)
K = CAM.K


def _points(rng: np.random.Generator, n: int, planar: bool) -> np.ndarray:
    """(n,3) world points ahead of the first camera: depths 4-12 m, or on a plane tilted about x."""
    uv = rng.uniform([-200, -150], [W + 200, H + 150], (n, 2))
    rays = np.hstack([uv, np.ones((n, 1))]) @ np.linalg.inv(K).T
    if planar:
        normal = np.array([0.0, -0.3, -1.0]) / np.hypot(0.3, 1.0)
        return rays * (-6.0 / (rays @ normal))[:, None]
    return rays * rng.uniform(4.0, 12.0, n)[:, None]


def _stream(seed: int, planar: bool, step: np.ndarray, n_frames: int = 25, n: int = 800, noise: float = 0.3,
            outliers: float = 0.0, yaw_per_frame: float = 0.0):
    """Frames k = 0.. of a camera moving by ``step`` (m, world = first camera) per frame -> list of
    (T_world_cam, Features). Every point keeps one random 256-bit descriptor, so matching is exact; a fraction
    ``outliers`` of each later frame's keypoints sit at random pixels (wrong matches)."""
    rng = np.random.default_rng(seed)
    P = _points(rng, n, planar)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    frames = []
    for k in range(n_frames):
        T_wc = make_T(so3_exp([0.0, yaw_per_frame * k, 0.0]), step * k)
        p = P @ inv_T(T_wc)[:3, :3].T + inv_T(T_wc)[:3, 3]
        uv = p[:, :2] / p[:, 2:3] @ K[:2, :2].T + K[:2, 2]
        vis = np.flatnonzero((p[:, 2] > 0.5) & np.all((uv >= 0) & (uv < [W, H]), axis=1))
        uv = uv[vis] + rng.normal(0.0, noise, (len(vis), 2))
        if k > 0 and outliers > 0:
            bad = rng.random(len(vis)) < outliers
            uv[bad] = rng.uniform([0, 0], [W, H], (int(bad.sum()), 2))
        m = len(vis)
        frames.append((T_wc, Features(uv.copy(), uv, desc[vis], np.zeros(m, np.int64), np.ones(m))))
    return frames


def _run(frames, cfg: InitConfig):
    """Feed the frames until the initialiser takes a pair -> (initialiser, frame index taken, map) or None."""
    init = MonoInitializer(CAM, cfg)
    slam_map = Map()
    for k, (_, feats) in enumerate(frames):
        kfs = init.try_initialize(slam_map, k, 0.1 * k, feats, StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy), BackendConfig(), False)
        if kfs is not None:
            return init, k, slam_map
    return None


def _median_parallax_deg(slam_map: Map) -> float:
    """Median angle between the rays of the two keyframes to every map point."""
    k0, k1 = (slam_map.keyframes[k] for k in sorted(slam_map.keyframes))
    X = slam_map.points_xyz(np.array(sorted(slam_map.points)))
    a = X - k0.T_world_cam[:3, 3]
    b = X - k1.T_world_cam[:3, 3]
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


SIDEWAYS = np.array([0.08, 0.0, 0.0])  # 8 cm per frame: parallax grows ~0.6 deg per frame at 8 m
FORWARD = np.array([0.02, 0.0, 0.25])  # driving: mostly along the optical axis


@pytest.mark.parametrize("planar,model", [(False, "essential"), (True, "homography")])
def test_model_selection_over_a_stream(planar, model):
    """A general scene initialises with the essential matrix, a plane with the homography (ORB-SLAM's score
    rule), and the motion found is the true one up to scale."""
    frames = _stream(0, planar, SIDEWAYS)
    init, k, slam_map = _run(frames, InitConfig(min_parallax_deg=1.0))
    assert init.result is not None and init.result.model == model
    T_true = inv_T(frames[k][0]) @ frames[0][0]  # T_cur_ref
    T_est = init.result.T_cur_ref
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3
    t_est, t_true = T_est[:3, 3], T_true[:3, 3]
    assert np.degrees(np.arccos(t_est @ t_true / np.linalg.norm(t_est) / np.linalg.norm(t_true))) < 2.0


@pytest.mark.parametrize("planar", [False, True])
def test_first_passing_frame_is_taken_without_a_target(planar):
    """target_parallax_deg 0 (the old rule): the first frame whose pair passes min_parallax_deg."""
    frames = _stream(1, planar, SIDEWAYS)
    init, k, slam_map = _run(frames, InitConfig(min_parallax_deg=1.0))
    assert init.result.parallax_deg >= 1.0
    earlier = _run(frames[:k], InitConfig(min_parallax_deg=1.0))
    assert earlier is None  # no earlier frame passed


@pytest.mark.parametrize("planar", [False, True])
def test_pair_choice_waits_for_the_target_parallax(planar):
    """With a target the initialiser lets passing frames go until the pair's parallax reaches it: a later frame,
    a wider first baseline, and the map points see that parallax."""
    frames = _stream(2, planar, SIDEWAYS)
    first, k_min, _ = _run(frames, InitConfig(min_parallax_deg=1.0))
    target = first.result.parallax_deg + 1.5
    init, k, slam_map = _run(frames, InitConfig(min_parallax_deg=1.0, target_parallax_deg=target))
    assert k > k_min
    assert init.result.parallax_deg >= target
    assert _median_parallax_deg(slam_map) == pytest.approx(init.result.parallax_deg, rel=0.05)


def test_pair_choice_takes_the_pair_before_it_is_lost():
    """Turning away, the views share fewer points each frame: the pair is taken once its matches fall below
    keep_matches_ratio of those at the first passing frame, before the (unreachable) target parallax."""
    frames = _stream(3, False, SIDEWAYS, yaw_per_frame=0.02, n_frames=30)
    cfg = InitConfig(min_parallax_deg=1.0, target_parallax_deg=45.0, keep_matches_ratio=0.7)
    init, k, slam_map = _run(frames, cfg)
    _, k_first, _ = _run(frames, InitConfig(min_parallax_deg=1.0))
    assert k > k_first and init.result.parallax_deg < 45.0
    assert init.pair_matches < 0.7 * init.first_pass_matches
    # the frame before still held enough matches: it was let go
    before = _run(frames[:k], cfg)
    assert before is None


def test_min_inlier_ratio_refuses_pairs_of_mostly_wrong_matches():
    """40 % of the later frames' keypoints at random pixels: taken without the test, refused with 0.8."""
    frames = _stream(4, False, SIDEWAYS, outliers=0.4)
    assert _run(frames, InitConfig(min_parallax_deg=1.0)) is not None
    assert _run(frames, InitConfig(min_parallax_deg=1.0, min_inlier_ratio=0.8)) is None


def test_forward_motion_initialises_with_essential_and_true_scale_ratio():
    """Driving forward: the pair is taken, the model is E, and the map's depths agree with the truth up to one
    scale (the ratio between near and far points is right)."""
    frames = _stream(5, False, FORWARD, n_frames=30)
    init, k, slam_map = _run(frames, InitConfig(min_parallax_deg=1.0, target_parallax_deg=2.0))
    assert init.result.model == "essential" and init.result.parallax_deg >= 2.0
    t = init.result.T_cur_ref[:3, 3]
    t_true = (inv_T(frames[k][0]) @ frames[0][0])[:3, 3]
    s = np.linalg.norm(t_true) / np.linalg.norm(t)
    X = slam_map.points_xyz(np.array(sorted(slam_map.points))) * s
    P = _points(np.random.default_rng(5), 800, False)  # the same draw as _stream's
    err = np.min(np.linalg.norm(X[:, None, :] - P[None, :, :], axis=2), axis=1)
    assert np.median(err / np.linalg.norm(X, axis=1)) < 0.03


def test_only_well_conditioned_points_are_kept():
    """point_min_parallax_deg: every point kept was triangulated under at least that parallax; the motion is
    the same as without the floor."""
    frames = _stream(6, False, SIDEWAYS)
    k = 8
    m_ref, m_cur = frames[0][1], frames[k][1]
    ids0 = {bytes(d): i for i, d in enumerate(m_ref.desc)}
    pairs = np.array([(ids0[bytes(d)], j) for j, d in enumerate(m_cur.desc) if bytes(d) in ids0])
    uv0, uv1 = m_ref.uv[pairs[:, 0]], m_cur.uv[pairs[:, 1]]
    base = initialize_two_view(uv0, uv1, K, InitConfig(min_parallax_deg=1.0))
    floor = initialize_two_view(uv0, uv1, K, InitConfig(min_parallax_deg=1.0, point_min_parallax_deg=3.0))
    assert base is not None and floor is not None
    assert 0 < floor.inliers.sum() < base.inliers.sum()
    T = floor.T_cur_ref
    X = floor.pts_ref[floor.inliers]
    c_cur = inv_T(T)[:3, 3]
    a, b = X, X - c_cur
    par = np.degrees(np.arccos(np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)))
    assert par.min() >= 3.0 - 1e-9
    dR = T[:3, :3].T @ base.T_cur_ref[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 1e-6
