"""Synthetic BA / pose-only problems with exact answers (numpy only)."""

from __future__ import annotations

import numpy as np

from vslam.backend.ba import BAProblem, StereoCamera
from vslam.backend.projection import project_stereo
from vslam.geometry.se3 import make_T, so3_exp, so3_log

CAM = StereoCamera(fx=450.0, fy=450.0, cx=320.0, cy=240.0, baseline=0.11)
W, H = 640, 480


def camera_path(rng: np.random.Generator, n_kf: int, length: float = 0.6) -> list[np.ndarray]:
    """n_kf T_world_cam along +x (``length`` metres), looking roughly along world +z, a few degrees of wobble."""
    out = []
    for i in range(n_kf):
        c = np.array([length * i / max(n_kf - 1, 1), 0.05 * np.sin(i), 0.03 * i])
        out.append(make_T(so3_exp(rng.normal(0.0, np.deg2rad(3.0), 3)), c))
    return out


def visible(T_world_cam: np.ndarray, pts: np.ndarray, cam: StereoCamera = CAM) -> np.ndarray:
    uv, _, z = project_stereo(T_world_cam, pts, cam)
    return (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)


def observe(poses: list[np.ndarray], pts: np.ndarray, pairs: list[tuple[int, int]], cam: StereoCamera = CAM):
    """Exact (kf, pt, uv, ur) arrays for the (keyframe index, point index) pairs."""
    kf = np.array([k for k, _ in pairs], dtype=np.int64)
    pt = np.array([j for _, j in pairs], dtype=np.int64)
    uv = np.zeros((len(pairs), 2))
    ur = np.zeros(len(pairs))
    for k in np.unique(kf):
        m = kf == k
        uv[m], ur[m], _ = project_stereo(poses[k], pts[pt[m]], cam)
    return kf, pt, uv, ur


def full_scene(rng: np.random.Generator, n_kf: int = 6, n_pts: int = 200, stereo_frac: float = 0.5):
    """Every keyframe sees every point (points 4-9 m ahead). -> (true poses, true points, BAProblem w/o noise)."""
    poses = camera_path(rng, n_kf)
    pts = np.column_stack([rng.uniform(-2.0, 2.6, n_pts), rng.uniform(-1.5, 1.5, n_pts), rng.uniform(4.0, 9.0, n_pts)])
    pairs = [(k, j) for k in range(n_kf) for j in np.flatnonzero(visible(poses[k], pts)).tolist()]
    return poses, pts, _problem(rng, poses, pts, pairs, stereo_frac)


def window(rng: np.random.Generator, n_kf: int = 10, obs_per_kf: int = 300, stereo_frac: float = 0.5, views: int = 2):
    """ORB-SLAM-like local window: each point seen by ``views`` consecutive keyframes, ~obs_per_kf obs each."""
    poses = camera_path(rng, n_kf, length=0.15 * n_kf)
    pts, pairs = [], []
    for j in range(n_kf * obs_per_kf // views):
        a = min(j % n_kf, n_kf - views)
        kfs = list(range(a, a + views))
        anchor = kfs[j % views]
        while True:
            uv = rng.uniform([20, 20], [W - 20, H - 20])
            z = rng.uniform(3.0, 12.0)
            p_c = np.array([(uv[0] - CAM.cx) / CAM.fx * z, (uv[1] - CAM.cy) / CAM.fy * z, z])
            p_w = poses[anchor][:3, :3] @ p_c + poses[anchor][:3, 3]
            if all(visible(poses[k], p_w[None])[0] for k in kfs):
                break
        pts.append(p_w)
        pairs += [(k, j) for k in kfs]
    return poses, np.array(pts), _problem(rng, poses, np.array(pts), pairs, stereo_frac)


def _problem(rng, poses, pts, pairs, stereo_frac) -> BAProblem:
    kf, pt, uv, ur = observe(poses, pts, pairs)
    ur[rng.random(ur.shape[0]) >= stereo_frac] = np.nan
    return BAProblem(
        poses={k: T.copy() for k, T in enumerate(poses)},
        fixed=set(),
        points={j: p.copy() for j, p in enumerate(pts)},
        obs_kf=kf,
        obs_pt=pt,
        obs_uv=uv,
        obs_ur=ur,
    )


def perturb_pose(rng: np.random.Generator, T: np.ndarray, trans_m: float, rot_deg: float) -> np.ndarray:
    """T with a random rotation of exactly rot_deg (about a random axis) and translation of trans_m metres."""
    a = rng.normal(size=3)
    d = rng.normal(size=3)
    dT = make_T(so3_exp(a / np.linalg.norm(a) * np.deg2rad(rot_deg)), d / np.linalg.norm(d) * trans_m)
    return T @ dT


def perturb(rng, problem: BAProblem, trans_m=0.02, rot_deg=1.0, pt_m=0.05) -> BAProblem:
    """Copy of problem with the non-fixed poses and all points perturbed (fixed poses untouched)."""
    poses = {
        k: (T.copy() if k in problem.fixed else perturb_pose(rng, T, trans_m, rot_deg)) for k, T in problem.poses.items()
    }
    points = {j: p + rng.normal(0.0, pt_m / np.sqrt(3), 3) for j, p in problem.points.items()}
    return BAProblem(poses, set(problem.fixed), points, problem.obs_kf.copy(), problem.obs_pt.copy(),
                     problem.obs_uv.copy(), problem.obs_ur.copy(), problem.obs_sigma)


def pose_problem(rng, n: int, stereo_frac: float):
    """One camera seeing ``n`` points 2-15 m away, uniformly over the image, exact measurements; a random
    ``1 - stereo_frac`` of them mono (ur NaN). -> (T_world_cam, world points (n,3), uv (n,2), ur (n,))."""
    T = camera_path(rng, 1)[0]
    uvc = rng.uniform([0, 0], [W, H], (n, 2))
    z = rng.uniform(2.0, 15.0, n)
    pc = np.column_stack([(uvc[:, 0] - CAM.cx) / CAM.fx * z, (uvc[:, 1] - CAM.cy) / CAM.fy * z, z])
    pw = pc @ T[:3, :3].T + T[:3, 3]
    uv, ur, _ = project_stereo(T, pw, CAM)
    ur[rng.random(n) >= stereo_frac] = np.nan
    return T, pw, uv, ur


def add_outliers(rng, uv: np.ndarray, ur: np.ndarray, frac: float, px: float = 30.0) -> np.ndarray:
    """Shift a random ``frac`` of the observations by ``px`` pixels (2-D for mono, 3-D for stereo); -> (N,) bool mask."""
    n = uv.shape[0]
    bad = np.zeros(n, dtype=bool)
    bad[rng.choice(n, int(round(frac * n)), replace=False)] = True
    for i in np.flatnonzero(bad):
        st = np.isfinite(ur[i])
        d = rng.normal(size=3 if st else 2)
        d *= px / np.linalg.norm(d)
        uv[i] += d[:2]
        if st:
            ur[i] += d[2]
    return bad


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """-> (translation error m, rotation error deg)."""
    ang = np.degrees(np.linalg.norm(so3_log(T_est[:3, :3].T @ T_true[:3, :3])))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(ang)
