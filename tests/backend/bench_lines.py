"""Cost of line landmarks in local BA (not a test; run ``python -m tests.backend.bench_lines``).

A 10-keyframe window of points (``_synth.window``: 300 obs per keyframe, 50 % stereo) plus ``--lines`` lines
each seen by ``--views`` consecutive keyframes, poses 1 cm / 0.3 deg off; BA with points only, with the
lines as one structureless factor ("window") and as GTSAM variables ("landmark"). Prints median CPU ms
(process time, so other jobs on the machine count less) and the per-call cost of the line factors.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from tests.backend import _synth as S  # noqa: E402
from vslam.backend.ba import BackendConfig, local_bundle_adjustment  # noqa: E402
from vslam.backend.line_ba import LineProblem  # noqa: E402
from vslam.geometry import plucker as pl  # noqa: E402
from vslam.geometry.se3 import inv_T  # noqa: E402


def line_window(rng: np.random.Generator, poses: list[np.ndarray], n_lines: int, views: int) -> LineProblem:
    K = np.array([[S.CAM.fx, 0, S.CAM.cx], [0, S.CAM.fy, S.CAM.cy], [0, 0, 1.0]])
    lines, kf, ln, seg = {}, [], [], []
    while len(lines) < n_lines:
        a0 = int(rng.integers(0, len(poses) - views + 1))
        kfs = list(range(a0, a0 + views))
        a = poses[a0][:3, :3] @ np.array([rng.uniform(-2, 2), rng.uniform(-1.5, 1.5), rng.uniform(3, 8)]) + poses[a0][:3, 3]
        b = a + rng.normal(0, 0.8, 3)
        if not all(S.visible(poses[k], np.stack([a, b])).all() for k in kfs):
            continue
        j = len(lines)
        lines[j] = pl.normalize(pl.from_points(a, b))
        for k in kfs:
            Tcw = inv_T(poses[k])
            pa, pb = K @ (Tcw[:3, :3] @ a + Tcw[:3, 3]), K @ (Tcw[:3, :3] @ b + Tcw[:3, 3])
            kf.append(k), ln.append(j), seg.append(np.r_[pa[:2] / pa[2], pb[:2] / pb[2]] + rng.normal(0, 0.5, 4))
    return LineProblem(lines, np.array(kf), np.array(ln), np.array(seg))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--lines", type=int, default=60)
    ap.add_argument("--views", type=int, default=4)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    poses, _, prob = S.window(rng, n_kf=10, obs_per_kf=300, views=2)
    prob.fixed = {0, 1}
    prob.obs_uv = prob.obs_uv + rng.normal(0, 0.5, prob.obs_uv.shape)
    lp = line_window(rng, poses, args.lines, args.views)
    noisy = S.perturb(rng, prob, trans_m=0.01, rot_deg=0.3, pt_m=0.02)
    cfg = BackendConfig()
    # RGB-D end-point depths (the truth read along the segments' end-point rays, 0.05 px virtual disparity)
    K_L = pl.line_projection_matrix(S.CAM.fx, S.CAM.fy, S.CAM.cx, S.CAM.cy)
    L = np.array([lp.lines[j] for j in lp.obs_line.tolist()])
    Lc = np.array([pl.transform(L[i], inv_T(poses[k])) for i, k in enumerate(lp.obs_kf.tolist())])
    rho = pl.inverse_depth(Lc[:, :3], Lc[:, 3:], pl.end_rays(lp.obs_seg, K_L))[0]
    lp_d = dataclasses.replace(lp, obs_rho=rho, depth_weight=S.CAM.fx * 0.08 / 0.05)
    for name, lines in (("points only", None), ("+ lines, window", lp), ("+ lines, window, depths", lp_d),
                        ("+ lines, landmark", dataclasses.replace(lp, mode="landmark"))):
        noisy.lines = lines
        ts, errs = [], []
        for _ in range(args.repeat):
            t0 = time.process_time()
            res = local_bundle_adjustment(noisy, S.CAM, cfg)
            ts.append(1e3 * (time.process_time() - t0))
        errs = [S.pose_error(res.poses[k], poses[k])[0] for k in res.poses]
        print(f"{name:20s} median {np.median(ts):7.1f} ms CPU (min {np.min(ts):7.1f}), {res.iterations} LM iterations, "
              f"max pose error {1e3 * max(errs):.2f} mm")


if __name__ == "__main__":
    main()
