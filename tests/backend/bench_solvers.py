"""Windowed LM (the back end's choice) against iSAM2 on a growing stereo map (not a test; run
``python -m tests.backend.bench_solvers``).

Issue 3 asks to measure iSAM2 / fixed-lag smoothing / windowed LM and choose. The scene: ``--kf`` keyframes
along a wobbly path, each point seen by 4-8 consecutive keyframes as a stereo-like measurement (0.7 px
noise on uL, uR, v independently, Huber), about 250 new points per keyframe. A keyframe arrives with a
tracked pose (the previous *estimate* composed with the true motion, plus 5 mm / 0.3 deg of noise) and its
new points at their first view's back-projection plus noise.

- windowed LM: ``local_bundle_adjustment`` per keyframe on the newest 8 keyframes; the older keyframes that
  see the window's points are held fixed (what ``LocalMapper.bundle_adjust`` builds);
- iSAM2: one ``ISAM2.update`` per keyframe with its new factors and variables (relinearise threshold 0.01,
  every update), the whole history kept, ``calculateEstimate`` each time;
- batch LM over everything once at the end: the accuracy floor.

Reported: keyframe position / rotation RMSE against the truth (the first keyframe is held, so no
alignment), mean and max ms per keyframe. BLAS/OpenMP are pinned to one thread.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

from tests.backend import _synth as S  # noqa: E402
from vslam.backend import factors as fx  # noqa: E402
from vslam.backend.ba import BackendConfig, BAProblem, local_bundle_adjustment  # noqa: E402
from vslam.backend.projection import measurement_matrix, project_stereo  # noqa: E402
from vslam.geometry.se3 import make_T, so3_exp  # noqa: E402


def scene(rng: np.random.Generator, n_kf: int, new_per_kf: int = 250, noise_px: float = 0.7):
    """-> true poses (list of (4,4)), true points (P,3), observations (kf, pt, uv (M,2), ur (M,))."""
    poses = [make_T(so3_exp(np.array([0.0, 0.02 * np.sin(0.3 * i), 0.0])), np.array([0.15 * i, 0.05 * np.sin(i), 0.0]))
             for i in range(n_kf)]
    pts, kf, pt = [], [], []
    for k in range(n_kf):
        for _ in range(new_per_kf):
            span = int(rng.integers(4, 9))
            kfs = list(range(k, min(k + span, n_kf)))
            while True:
                uv = rng.uniform([40, 40], [S.W - 40, S.H - 40])
                z = rng.uniform(2.0, 10.0)
                p_c = np.array([(uv[0] - S.CAM.cx) / S.CAM.fx * z, (uv[1] - S.CAM.cy) / S.CAM.fy * z, z])
                p_w = poses[k][:3, :3] @ p_c + poses[k][:3, 3]
                vis = [kk for kk in kfs if S.visible(poses[kk], p_w[None])[0]]
                if len(vis) >= min(2, len(kfs)):
                    break
            pts.append(p_w)
            kf += vis
            pt += [len(pts) - 1] * len(vis)
    pts, kf, pt = np.array(pts), np.array(kf), np.array(pt)
    uv, ur = np.zeros((len(kf), 2)), np.zeros(len(kf))
    for k in range(n_kf):
        m = kf == k
        uv[m], ur[m], _ = project_stereo(poses[k], pts[pt[m]], S.CAM)
    uv += rng.normal(0, noise_px, uv.shape)
    ur += rng.normal(0, noise_px, ur.shape)
    return poses, pts, (kf, pt, uv, ur)


def _errors(est: dict[int, np.ndarray], poses) -> tuple[float, float]:
    e = [S.pose_error(est[k], poses[k]) for k in sorted(est)]
    return float(np.sqrt(np.mean([t**2 for t, _ in e]))), float(np.sqrt(np.mean([r**2 for _, r in e])))


def _arrivals(rng, poses, pts, obs):
    """Per keyframe: (tracked-pose noise (4,4) delta, ids of points first seen there, their initial xyz)."""
    kf, pt, uv, ur = obs
    first = {}
    for k, j in zip(kf.tolist(), pt.tolist()):
        first.setdefault(j, k)
    out = []
    for k in range(len(poses)):
        new = np.array(sorted(j for j, f in first.items() if f == k), np.int64)
        noise = make_T(so3_exp(rng.normal(0, np.deg2rad(0.3) / np.sqrt(3), 3)), rng.normal(0, 0.005 / np.sqrt(3), 3))
        out.append((noise, new, pts[new] + rng.normal(0, 0.03, (len(new), 3))))
    return out


def run_windowed(poses, pts, obs, arrivals, window: int = 8):
    kf, pt, uv, ur = obs
    est_T: dict[int, np.ndarray] = {0: poses[0].copy()}
    est_P: dict[int, np.ndarray] = {}
    ms = []
    for k in range(len(poses)):
        noise, new, init = arrivals[k]
        if k > 0:
            est_T[k] = est_T[k - 1] @ np.linalg.inv(poses[k - 1]) @ poses[k] @ noise
        est_P.update({int(j): x for j, x in zip(new, init)})
        t0 = time.perf_counter()
        win = [kk for kk in range(max(0, k - window + 1), k + 1)]
        seen = np.isin(kf, win)
        wpts = np.unique(pt[seen])
        sel = np.isin(pt, wpts) & (kf <= k)
        fixed = set(np.unique(kf[sel]).tolist()) - set(win) | {0}
        prob = BAProblem({int(kk): est_T[int(kk)] for kk in np.unique(kf[sel]).tolist() + [0]}, fixed,
                         {int(j): est_P[int(j)] for j in wpts}, kf[sel], pt[sel], uv[sel], ur[sel])
        res = local_bundle_adjustment(prob, S.CAM, BackendConfig())
        est_T.update(res.poses)
        est_P.update(res.points)
        ms.append(1e3 * (time.perf_counter() - t0))
    return est_T, ms


def run_isam2(poses, pts, obs, arrivals):
    kf, pt, uv, ur = obs
    meas, st = measurement_matrix(uv, ur)
    builder = fx.FactorBuilder(S.CAM, BackendConfig().huber_k)
    ip = gtsam.ISAM2Params()
    ip.setRelinearizeThreshold(0.01)
    ip.relinearizeSkip = 1
    isam = gtsam.ISAM2(ip)
    est_T = {0: poses[0].copy()}
    ms = []
    for k in range(len(poses)):
        noise, new, init = arrivals[k]
        if k > 0:
            est_T[k] = est_T[k - 1] @ np.linalg.inv(poses[k - 1]) @ poses[k] @ noise
        t0 = time.perf_counter()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(builder.hold(fx.X(0), poses[0]))
        values.insert(fx.X(k), fx.pose3(est_T[k]))
        for j, x in zip(new.tolist(), init):
            values.insert(fx.L(j), x)
        m = np.flatnonzero(kf == k)
        for f in builder.factors(kf[m], pt[m], meas[m], st[m], np.full(len(m), BackendConfig().pixel_sigma)):
            graph.add(f)
        isam.update(graph, values)
        est = isam.calculateEstimate()
        for kk in range(k + 1):
            est_T[kk] = est.atPose3(fx.X(kk)).matrix()
        ms.append(1e3 * (time.perf_counter() - t0))
    return est_T, ms


def run_batch(poses, pts, obs, est_T):
    kf, pt, uv, ur = obs
    prob = BAProblem({k: est_T[k] for k in est_T}, {0}, {j: pts[j] + 0.0 for j in range(len(pts))}, kf, pt, uv, ur)
    t0 = time.perf_counter()
    res = local_bundle_adjustment(prob, S.CAM, BackendConfig(max_iterations=20, refine_iterations=10))
    out = {0: poses[0], **res.poses}
    return out, 1e3 * (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kf", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    poses, pts, obs = scene(rng, a.kf)
    arrivals = _arrivals(rng, poses, pts, obs)
    print(f"{a.kf} keyframes, {len(pts)} points, {len(obs[0])} stereo observations")
    for name, fn in (("windowed LM (8 kf)", run_windowed), ("iSAM2", run_isam2)):
        est, ms = fn(poses, pts, obs, arrivals)
        t, r = _errors(est, poses)
        print(f"{name:20s}: keyframe RMSE {1e3 * t:6.2f} mm / {r:.3f} deg; ms per keyframe mean {np.mean(ms):7.1f}, "
              f"max {np.max(ms):7.1f}, last 5 {np.mean(ms[-5:]):7.1f}")
        if name.startswith("iSAM2"):
            floor, ms_b = run_batch(poses, pts, obs, est)
            t, r = _errors(floor, poses)
            print(f"{'batch LM (all)':20s}: keyframe RMSE {1e3 * t:6.2f} mm / {r:.3f} deg; {ms_b:.0f} ms once")


if __name__ == "__main__":
    main()
