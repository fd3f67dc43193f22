"""Visual-inertial local BA (``vslam.backend.inertial``) on a small exact problem.

The rig follows the synthetic generator's analytic motion (exact IMU, optional realistic noise); 8 keyframes
0.25 s apart observe random points (half stereo-like, half monocular); poses, velocities and biases start
perturbed and the first keyframe is held.
"""

from __future__ import annotations

import numpy as np
import pytest

from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera
from vslam.backend.inertial import ImuChain, InertialBAConfig, initial_bias_covariance, visual_inertial_bundle_adjustment
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.geometry.se3 import inv_T, make_T, so3_exp
from vslam.inertial.preintegration import make_params

CAM = StereoCamera(262.5, 262.5, 159.5, 119.5, 0.1)


def _problem(noise: bool, seed: int = 0):
    seq = SyntheticSequence(SyntheticConfig(n_frames=70, width=320, height=240, fx=262.5, fy=262.5, n_movers=0,
                                            imu_noise_enabled=noise, seed=seed), sensor="stereo")
    rng = np.random.default_rng(seed)
    idx = np.arange(0, 64, 8)  # 8 keyframes, 0.267 s apart
    t = seq.timestamps()[idx]
    Twc = seq.groundtruth().poses[idx]
    T_bc = seq.calibration.T_body_cam0
    truth = seq.imu_truth()
    body = seq.motion.body_state(t - t[0])
    j = np.searchsorted(truth.t, t)
    bias = np.hstack([truth.accel_bias[j], truth.gyro_bias[j]])
    # points 2-6 m in front of each keyframe camera, observed by every keyframe that sees them
    pts = []
    for T in Twc:
        uv = rng.uniform([10, 10], [310, 230], (40, 2))
        z = rng.uniform(2.0, 6.0, 40)
        Xc = np.stack([(uv[:, 0] - CAM.cx) / CAM.fx * z, (uv[:, 1] - CAM.cy) / CAM.fy * z, z], 1)
        pts.append(Xc @ T[:3, :3].T + T[:3, 3])
    P = np.vstack(pts)
    okf, opt, ouv, our = [], [], [], []
    for k, T in enumerate(Twc):
        Tcw = inv_T(T)
        Xc = P @ Tcw[:3, :3].T + Tcw[:3, 3]
        u, v = CAM.fx * Xc[:, 0] / Xc[:, 2] + CAM.cx, CAM.fy * Xc[:, 1] / Xc[:, 2] + CAM.cy
        vis = (Xc[:, 2] > 0.5) & (u > 0) & (u < 319) & (v > 0) & (v < 239)
        for p in np.flatnonzero(vis):
            okf.append(k), opt.append(p)
            ouv.append([u[p], v[p]] + rng.normal(0, 0.5, 2))
            our.append(u[p] - CAM.fx * CAM.baseline / Xc[p, 2] + rng.normal(0, 0.5) if p % 2 == 0 else np.nan)
    return seq, t, Twc, T_bc, body.v, bias, P, np.array(okf), np.array(opt), np.array(ouv), np.array(our)


def _perturb(T, rng, rot=0.02, trans=0.05):
    return T @ make_T(so3_exp(rng.normal(0, rot, 3)), rng.normal(0, trans, 3))


@pytest.mark.parametrize("noise", [False, True])
def test_vi_ba_recovers_poses_velocities_biases(noise):
    seq, t, Twc, T_bc, vel, bias, P, okf, opt, ouv, our = _problem(noise)
    rng = np.random.default_rng(1)
    K = len(t)
    poses = {k: (Twc[k] if k == 0 else _perturb(Twc[k], rng)) for k in range(K)}
    pts = {j: P[j] + rng.normal(0, 0.05, 3) for j in range(len(P))}
    problem = BAProblem(poses, {0}, pts, okf, opt, ouv, our)
    v0 = vel + rng.normal(0, 0.2, vel.shape)
    b0 = np.zeros((K, 6))  # biases start at zero; truth is (0.04, -0.03, 0.02) m/s^2, (2, -1.5, 1) mrad/s
    params = make_params(seq.calibration.imu)
    chain = ImuChain(np.arange(K), t, v0, b0, seq.imu(), params, T_bc,
                     prior_v=np.eye(3) * 1.0, prior_b=initial_bias_covariance(0.1, 0.01))
    res = visual_inertial_bundle_adjustment(problem, chain, CAM, BackendConfig(max_iterations=10), InertialBAConfig(),
                                            marginal_for=1)
    pos_err = max(np.linalg.norm(res.ba.poses[k][:3, 3] - Twc[k][:3, 3]) for k in range(1, K))
    vel_err = max(np.linalg.norm(res.velocity[k] - vel[k]) for k in range(K))
    bg_err = max(np.linalg.norm(res.bias[k][3:] - bias[k, 3:]) for k in range(K))
    ba_err = max(np.linalg.norm(res.bias[k][:3] - bias[k, :3]) for k in range(K))
    # measured (0.5 px pixel noise; exact IMU / realistic IMU noise): position 3.0 / 2.9 mm, velocity 3.9 / 7.7 mm/s,
    # gyro bias 0.74 / 0.68 mrad/s (start: 2.7), accel bias 2.3 / 11.9 mm/s^2 (start: 54). Without pixel noise
    # and IMU noise every error is below 0.5 mm(/s) -- the body/camera/IMU model is exact.
    assert pos_err < 0.006
    assert vel_err < 0.015
    assert bg_err < 1.2e-3
    assert ba_err < 0.025
    assert res.ba.inliers.mean() > 0.95
    cov_v, cov_b = res.marginal[1]
    assert cov_v.shape == (3, 3) and cov_b.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov_v) > 0)


def test_imu_factors_fix_a_mono_window_scale():
    """Monocular observations alone leave the window's scale free; the IMU factors make it metric."""
    seq, t, Twc, T_bc, vel, bias, P, okf, opt, ouv, our = _problem(True)
    K = len(t)
    s = 0.8  # start from a 20 % too small map around the first keyframe
    c0 = Twc[0][:3, 3]
    poses = {k: Twc[k].copy() for k in range(K)}
    for k in range(1, K):
        poses[k][:3, 3] = c0 + s * (Twc[k][:3, 3] - c0)
    pts = {j: c0 + s * (P[j] - c0) for j in range(len(P))}
    problem = BAProblem(poses, {0}, pts, okf, opt, ouv, np.full(len(okf), np.nan))
    chain = ImuChain(np.arange(K), t, s * vel, np.zeros((K, 6)), seq.imu(), make_params(seq.calibration.imu), T_bc,
                     prior_v=np.eye(3) * 1.0, prior_b=initial_bias_covariance(0.1, 0.01))
    res = visual_inertial_bundle_adjustment(problem, chain, StereoCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, 0.0),
                                            BackendConfig(max_iterations=15), InertialBAConfig(max_iterations=15))
    d_est = np.linalg.norm(res.ba.poses[K - 1][:3, 3] - c0)
    d_true = np.linalg.norm(Twc[K - 1][:3, 3] - c0)
    assert abs(d_est / d_true - 1) < 0.02  # measured 0.9967 (start 0.8)
