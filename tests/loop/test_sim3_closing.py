"""Monocular loop closing as a similarity: a map with injected scale + yaw drift, closed by the loop closer."""

from __future__ import annotations

import dataclasses

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.backend.pose_graph import sim_matrix
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.geometry.se3 import inv_T, make_T, so3_exp
from vslam.loop.closing import LoopCloser
from vslam.loop.config import LoopConfig
from vslam.mapping.map import Map
from vslam.tracking.frame_log import FrameLog

CAM = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
N_KF, EARLY, LATE = 40, 5, 34  # keyframes; landmarks seen by kf <= EARLY and kf >= LATE get a point per side


def _true_poses() -> list[np.ndarray]:
    """Keyframes on a circle of radius 2 m, each looking radially out at a cylindrical wall 5 m from the centre."""
    out = []
    for k in range(N_KF):
        a = 2 * np.pi * k / N_KF
        z = np.array([np.sin(a), 0.0, np.cos(a)])
        y = np.array([0.0, -1.0, 0.0])
        out.append(make_T(np.stack([np.cross(y, z), y, z], axis=1), 2.0 * z))
    return out


def _drifted(true: list[np.ndarray], rng) -> tuple[list[np.ndarray], np.ndarray]:
    """Monocular odometry: every step 1 % shorter (scale drift) and a small yaw bias."""
    est, scale = [true[0].copy()], [1.0]
    bias = make_T(so3_exp(np.array([0.0, 0.004, 0.0])), np.zeros(3))
    for a, b in zip(true[:-1], true[1:]):
        scale.append(scale[-1] * 0.99)
        rel = inv_T(a) @ b @ bias @ make_T(so3_exp(rng.normal(0, 2e-4, 3)), np.zeros(3))
        rel[:3, 3] *= scale[-1]
        est.append(est[-1] @ rel)
    return est, np.array(scale)


def _project(T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = (X - T[:3, 3]) @ T[:3, :3]
    z = Xc[:, 2]
    uv = np.stack([CAM.fx * Xc[:, 0] / np.maximum(z, 1e-9) + CAM.cx, CAM.fy * Xc[:, 1] / np.maximum(z, 1e-9) + CAM.cy], 1)
    vis = (z > 0.5) & (uv[:, 0] > 5) & (uv[:, 0] < 634) & (uv[:, 1] > 5) & (uv[:, 1] < 474)
    return uv, vis


def _drifted_map(seed: int = 0):
    rng = np.random.default_rng(seed)
    true = _true_poses()
    est, scale = _drifted(true, rng)
    n = 4000
    a, h = rng.uniform(0, 2 * np.pi, n), rng.uniform(-1.5, 1.5, n)
    X = np.stack([5 * np.sin(a), h, 5 * np.cos(a)], 1)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    m = Map()
    obs: dict[int, list[tuple[int, int]]] = {}  # landmark -> [(kf, keypoint)]
    for k, T in enumerate(true):
        uv, vis = _project(T, X)
        lm = np.flatnonzero(vis)
        uvk = uv[lm] + rng.normal(0, 0.5, (len(lm), 2))
        f = Features(uvk.copy(), uvk, desc[lm], np.zeros(len(lm), np.int64), np.ones(len(lm)))
        nan = np.full(len(lm), np.nan)
        m.add_keyframe(k, float(k), est[k], f, nan, nan.copy())
        for i, l in enumerate(lm):
            obs.setdefault(int(l), []).append((k, i))
    S_est = {k: sim_matrix(est[k], scale[k]) @ np.linalg.inv(sim_matrix(true[k])) for k in range(N_KF)}
    for l, ob in obs.items():
        early = [o for o in ob if o[0] <= EARLY]
        sides = [early, [o for o in ob if o not in early]] if early and any(o[0] >= LATE for o in ob) else [ob]
        for side in sides:  # the late side re-discovers the early landmarks: a duplicate in the drifted frame
            if len(side) < 2:
                continue
            f0 = side[0][0]
            mp = m.add_point(S_est[f0][:3, :3] @ X[l] + S_est[f0][:3, 3], f0, side[0][1])
            for k, i in side[1:]:
                m.add_observation(mp.id, k, i)
    return m, true, est, scale


def _ate(poses: list[np.ndarray], true: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((p[:3, 3] - t[:3, 3]) ** 2) for p, t in zip(poses, true)])))


def test_monocular_loop_is_closed_as_a_similarity() -> None:
    m, true, est, scale = _drifted_map()
    cfg = dataclasses.replace(LoopConfig(enabled=True), global_ba=False, local_ba=False)
    lc = LoopCloser(m, CAM, StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, 0.0), "mono", cfg, BackendConfig())
    log = FrameLog(m)
    lc.frames = log
    q = m.keyframes[N_KF - 1]
    T_frame = q.T_world_cam @ make_T(np.eye(3), np.array([0.0, 0.0, 0.05 * scale[-1]]))  # a frame 5 cm ahead
    log.record(999, q.id, T_frame)
    own = q.point_ids[q.point_ids >= 0]
    match = lc.verifier.verify(m, q.features, q.ur, 0, exclude_points=own, max_kf=EARLY + 3)
    assert match is not None and match.n_inliers > 60
    s = lc.loop_scale(q, match)
    assert s is not None and abs(s * scale[-1] - 1) < 0.03  # measured 1.466 for a true 1 / 0.676 = 1.480
    before = _ate([kf.T_world_cam for kf in m.keyframes.values()], true)
    lc.correct_sim3(q, match, s)
    after = _ate([m.keyframes[k].T_world_cam for k in range(N_KF)], true)
    assert before > 0.3 and after < 0.15 * before, (before, after)  # measured 0.505 -> 0.031 m
    assert abs(lc.last_scale * scale[-1] - 1) < 0.05  # the query keyframe took ~1 / its drifted scale
    # the frame keeps its place relative to its keyframe, at the corrected scale: 5 cm ahead of it again
    T_new = log.poses([999])[0]
    ahead = inv_T(m.keyframes[N_KF - 1].T_world_cam) @ T_new
    assert abs(ahead[2, 3] - 0.05) < 0.005 and log.moved
    # the drifted duplicates now lie on the old points they duplicate (fusion merged or moved them)
    dup = [(int(q.point_ids[k]), int(match.point_ids[k])) for k in np.flatnonzero(match.point_ids >= 0)
           if q.point_ids[k] >= 0 and int(q.point_ids[k]) in m.points and int(match.point_ids[k]) in m.points]
    gaps = [np.linalg.norm(m.points[a].xyz - m.points[b].xyz) for a, b in dup]
    assert gaps and np.median(gaps) < 0.05


def test_rigid_correction_leaves_the_scale_drift() -> None:
    """The same loop through the SE3 graph (what RGB-D/stereo use): the scale error stays in the map."""
    m, true, est, scale = _drifted_map()
    cfg = dataclasses.replace(LoopConfig(enabled=True), global_ba=False, local_ba=False)
    lc = LoopCloser(m, CAM, StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, 0.0), "mono", cfg, BackendConfig())
    q = m.keyframes[N_KF - 1]
    match = lc.verifier.verify(m, q.features, q.ur, 0, exclude_points=q.point_ids[q.point_ids >= 0], max_kf=EARLY + 3)
    lc.correct(q, match)
    rigid = _ate([m.keyframes[k].T_world_cam for k in range(N_KF)], true)
    m2, *_ = _drifted_map()
    lc2 = LoopCloser(m2, CAM, lc.verifier.stereo_cam, "mono", cfg, BackendConfig())
    q2 = m2.keyframes[N_KF - 1]
    lc2.correct_sim3(q2, match, lc2.loop_scale(q2, match))
    assert _ate([m2.keyframes[k].T_world_cam for k in range(N_KF)], true) < 0.09 * rigid  # measured 0.031 vs 0.532 m (bound 1.5x)


def test_global_ba_after_a_monocular_loop_keeps_the_correction() -> None:
    """The default path (fusion + global BA with monocular projection factors) after the Sim3 graph."""
    from vslam.mapping.local_mapping import LocalMapper, MappingConfig

    m, true, _, _ = _drifted_map()
    sc = StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, 0.0)
    mapper = LocalMapper(m, CAM, sc, "mono", MappingConfig(), BackendConfig())
    lc = LoopCloser(m, CAM, sc, "mono", LoopConfig(enabled=True), BackendConfig(), mapper)
    q = m.keyframes[N_KF - 1]
    match = lc.verifier.verify(m, q.features, q.ur, 0, exclude_points=q.point_ids[q.point_ids >= 0], max_kf=EARLY + 3)
    before = _ate([m.keyframes[k].T_world_cam for k in range(N_KF)], true)
    n_before = len(m.points)
    lc.correct_sim3(q, match, lc.loop_scale(q, match))
    assert len(m.points) < n_before  # duplicates across the loop were merged
    assert _ate([m.keyframes[k].T_world_cam for k in range(N_KF)], true) < 0.15 * before
