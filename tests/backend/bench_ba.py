"""Timings of local BA and pose-only refinement (not a test; run ``python -m tests.backend.bench_ba``).

Pins BLAS/OpenMP to one thread before numpy is imported, runs each case ``--repeat`` times and prints
the median (and min) wall time. Also times the alternatives the backend decided against: fixed keyframes
held by NonlinearEqualityPose3, and pose-only refinement as a GTSAM graph; and local BA's numpy solver
(``BackendConfig.solver = "numpy"``).
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
from vslam.backend.ba import BackendConfig, local_bundle_adjustment, optimize_pose  # noqa: E402
from vslam.backend.projection import chi2_thresholds, measurement_matrix, transform_points, whitened_sq_errors  # noqa: E402
from vslam.geometry.se3 import inv_T  # noqa: E402


def _stats(ts: list[float]) -> str:
    return f"median {np.median(ts):7.2f} ms  (min {np.min(ts):7.2f})"


def bench_local_ba(repeat: int, n_kf: int, obs_per_kf: int, views: int, outliers: float) -> None:
    rng = np.random.default_rng(0)
    if views:
        poses, pts, prob = S.window(rng, n_kf=n_kf, obs_per_kf=obs_per_kf, views=views)
        name = f"window {n_kf} kf x {obs_per_kf} obs, {views} views/pt"
    else:
        poses, pts, prob = S.full_scene(rng, n_kf=n_kf, n_pts=obs_per_kf)
        name = f"full scene {n_kf} kf x {obs_per_kf} pts, every pt in every kf"
    prob.fixed = {0, 1}
    prob.obs_uv += rng.normal(0.0, 0.5, prob.obs_uv.shape)
    prob.obs_ur += rng.normal(0.0, 0.5, prob.obs_ur.shape)
    bad = S.add_outliers(rng, prob.obs_uv, prob.obs_ur, outliers)
    p = S.perturb(rng, prob)
    for label, sigma, solver in (("prior 1e-6 (default)", 1e-6, "gtsam"), ("NonlinearEquality", None, "gtsam"),
                                 ("numpy Schur solver", 1e-6, "numpy")):
        fx.FIXED_WITH_PRIOR_SIGMA = sigma
        runs = [local_bundle_adjustment(p, S.CAM, BackendConfig(solver=solver)) for _ in range(repeat)]
        r = runs[-1]
        terr = max(S.pose_error(r.poses[k], poses[k])[0] for k in r.poses)
        stages = {k: np.median([x.ms[k] for x in runs]) for k in ("build", "optimize", "classify")}
        print(
            f"local BA {name} ({len(p.obs_kf)} obs, {len(p.points)} pts, {outliers:.0%} outliers), fixed={label}: "
            f"{_stats([x.ms['total'] for x in runs])}; {', '.join(f'{k} {v:.1f}' for k, v in stages.items())}; "
            f"{r.iterations} it; max pose err {1e3 * terr:.2f} mm; outliers found {np.mean(~r.inliers[bad]):.3f}, "
            f"false pos {np.mean(~r.inliers[~bad]):.4f}"
        )
    fx.FIXED_WITH_PRIOR_SIGMA = 1e-6


def _pose_problem(rng, n: int, outliers: float = 0.2, noise_px: float = 0.3):
    T = S.camera_path(rng, 1)[0]
    uvc = rng.uniform([0, 0], [S.W, S.H], (n, 2))
    z = rng.uniform(2.0, 20.0, n)
    pc = np.column_stack([(uvc[:, 0] - S.CAM.cx) / S.CAM.fx * z, (uvc[:, 1] - S.CAM.cy) / S.CAM.fy * z, z])
    pw = pc @ T[:3, :3].T + T[:3, 3]
    uv, ur, _ = S.project_stereo(T, pw, S.CAM)
    ur[rng.random(n) < 0.5] = np.nan
    uv += rng.normal(0.0, noise_px, uv.shape)
    ur += rng.normal(0.0, noise_px, n)
    bad = S.add_outliers(rng, uv, ur, outliers)
    return T, pw, uv, ur, bad, S.perturb_pose(rng, T, 0.03, 2.0)


def gtsam_pose_only(T0, pw, uv, ur, camera, cfg):
    """The alternative: ORB-SLAM's 4 rounds as GTSAM graphs, points held by tight priors (not shipped)."""
    meas, stereo = measurement_matrix(uv, ur)
    n = pw.shape[0]
    sig = np.full(n, cfg.pixel_sigma)
    robust = fx.FactorBuilder(camera, cfg.huber_k).factors(np.zeros(n, int), np.arange(n), meas, stereo, sig)
    plain_b = fx.FactorBuilder(camera, 1e9)  # Huber with k = 1e9 sigmas: plain least squares in the last round
    plain = plain_b.factors(np.zeros(n, int), np.arange(n), meas, stereo, sig)
    hold = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
    thr = chi2_thresholds(stereo, cfg.chi2_mono, cfg.chi2_stereo)
    pose, active = fx.pose3(T0), np.ones(n, bool)
    for rnd in range(cfg.pose_rounds):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(fx.X(0), pose)
        for j in np.flatnonzero(active).tolist():
            graph.add((robust if rnd < cfg.pose_rounds - 1 else plain)[j])
            graph.add(gtsam.PriorFactorPoint3(fx.L(j), pw[j], hold))
            values.insert(fx.L(j), pw[j])
        pose = gtsam.LevenbergMarquardtOptimizer(graph, values, fx.lm_params(cfg.pose_iterations)).optimize().atPose3(fx.X(0))
        chi2, _ = whitened_sq_errors(transform_points(inv_T(fx.pose_matrix(pose)), pw), meas, stereo, sig, camera)
        active = chi2 <= thr
    return fx.pose_matrix(pose), active


def bench_pose_only(repeat: int) -> None:
    cfg = BackendConfig()
    for n in (300, 500):
        rng = np.random.default_rng(n)
        T, pw, uv, ur, bad, T0 = _pose_problem(rng, n)
        for label, fn in (("numpy", optimize_pose), ("gtsam", gtsam_pose_only)):
            ts = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                Te, inl = fn(T0, pw, uv, ur, S.CAM, cfg)
                ts.append(1e3 * (time.perf_counter() - t0))
            dt, dr = S.pose_error(Te, T)
            print(
                f"pose-only {label:5s} {n} pts, 20 % outliers, 0.3 px noise: {_stats(ts)}; "
                f"err {1e3 * dt:.3f} mm {dr:.4f} deg; "
                f"outliers found {np.mean(~inl[bad]):.3f}, false pos {np.mean(~inl[~bad]):.3f}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    bench_pose_only(max(args.repeat * 4, 20))
    bench_local_ba(args.repeat, 10, 300, 2, 0.05)
    bench_local_ba(args.repeat, 10, 300, 4, 0.05)
    bench_local_ba(args.repeat, 6, 200, 0, 0.05)


if __name__ == "__main__":
    main()
