"""Dynamic visual-inertial alignment: scale, gravity, velocities and gyro bias from up-to-scale keyframe poses.

The loosely coupled initialisation of VINS-Mono (Qin et al., T-RO 2018,
Sec. V-B) and ORB-SLAM3's first inertial init (Campos et al., T-RO 2021,
Sec. V-B), solved in closed form:

1. gyro bias: the visual relative rotations R_bi^T R_bj must equal the
   preintegrated ΔR_ij(b_g); Gauss-Newton on the stacked rotation residuals
   (ΔR is first-order corrected in the bias by gtsam, so 2-3 steps suffice);
2. one linear least-squares solve for the K velocities, the gravity vector in
   the visual frame and the metric scale from the preintegrated Δp, Δv
   (VINS-Mono eq. 13, written in the visual world frame), rows whitened by
   the preintegration covariance;
3. gravity refined on the sphere |g| = 9.81 with a 2-D tangent update
   (VINS-Mono "RefineGravity"), re-solving velocities, scale and (with a
   prior, as ORB-SLAM3's inertial-only step does) the accelerometer bias.

Pure numpy plus gtsam's preintegrated measurements; no factor graph.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field

import gtsam
import numpy as np

from vslam.data.types import ImuSamples
from vslam.errors import InertialError
from vslam.geometry.se3 import so3_exp, so3_log
from vslam.inertial.preintegration import make_bias, preintegrate

MIN_KEYFRAMES = 4  # 6(K-1) equations >= 3K + 4 unknowns


@dataclass(frozen=True)
class ViAlignment:
    """Alignment of a visual (up-to-scale, arbitrary-gravity) frame to the metric, gravity-aligned world.

    scale: metric length = scale * visual length.
    R_world_visual: (3,3), rotates visual-frame vectors so gravity is (0, 0, -g) (minimal rotation, yaw free).
    velocities: (K,3) m/s of the body at each keyframe, world frame.
    gyro_bias: (3,) rad/s.
    gravity_visual: (3,) m/s^2, the gravity vector found in the visual frame (|g| fixed).
    rotation_rms_rad: rms rotation residual after the gyro-bias fit (rad).
    residual_rms: rms of the final whitened linear system (in IMU-noise sigmas).
    accel_bias: (3,) m/s^2, the starting accel bias plus the estimated change (unchanged when not estimated).
    """

    scale: float
    R_world_visual: np.ndarray
    velocities: np.ndarray
    gyro_bias: np.ndarray
    gravity_visual: np.ndarray
    rotation_rms_rad: float
    residual_rms: float
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def metric_poses(self, T_visual_cam: np.ndarray) -> np.ndarray:
        """(K,4,4) up-to-scale visual poses -> metric T_world_cam in the gravity-aligned world (same origin)."""
        T = np.array(T_visual_cam, dtype=np.float64, copy=True)
        T[:, :3, :3] = self.R_world_visual @ T[:, :3, :3]
        T[:, :3, 3] = self.scale * T[:, :3, 3] @ self.R_world_visual.T
        return T


def _deltas(pim: gtsam.PreintegratedCombinedMeasurements, bias: gtsam.imuBias.ConstantBias) -> tuple[np.ndarray, ...]:
    """Bias-corrected (ΔR (3,3), Δp (3,), Δv (3,), dt, n_gravity (3,)) of a pim via gtsam's own predict.

    Predicting from the identity state adds 0.5 g dt^2 and g dt; g is read back from the pim at its
    linearisation bias (where the correction is zero), so the caller need not pass the params.
    """
    dt = float(pim.deltaTij())
    zero = gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3))
    n_g = 2.0 * (np.asarray(pim.predict(zero, pim.biasHat()).position()) - np.asarray(pim.deltaPij())) / dt**2
    out = pim.predict(zero, bias)
    return (out.attitude().matrix(), np.asarray(out.position()) - 0.5 * n_g * dt**2,
            np.asarray(out.velocity()) - n_g * dt, dt, n_g)


def _with_gyro(bias: gtsam.imuBias.ConstantBias, bg: np.ndarray) -> gtsam.imuBias.ConstantBias:
    return make_bias(np.asarray(bias.accelerometer()), bg)


def _rotation_residuals(pims: Seq, R_body: np.ndarray, bias0: gtsam.imuBias.ConstantBias, bg: np.ndarray) -> np.ndarray:
    """(K-1, 3) Log(ΔR(bg)^T R_bi^T R_bj), rad."""
    out = np.empty((len(pims), 3))
    for k, pim in enumerate(pims):
        dR = _deltas(pim, _with_gyro(bias0, bg))[0]
        out[k] = so3_log(dR.T @ R_body[k].T @ R_body[k + 1])
    return out


def estimate_gyro_bias(pims: Seq, R_body: np.ndarray, bias0: gtsam.imuBias.ConstantBias,
                       iterations: int = 3, h: float = 1e-4) -> tuple[np.ndarray, float]:
    """Gyro bias (3,) rad/s that best explains the visual relative rotations, and the rms residual (rad).

    R_body: (K,3,3) body orientations in the visual frame. Numeric Jacobian of the
    residual in the bias (central differences; gtsam's bias correction is smooth).
    """
    bg = np.asarray(bias0.gyroscope(), dtype=np.float64).copy()
    for _ in range(iterations):
        r = _rotation_residuals(pims, R_body, bias0, bg).reshape(-1)
        J = np.empty((r.size, 3))
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            J[:, a] = (_rotation_residuals(pims, R_body, bias0, bg + e).reshape(-1)
                       - _rotation_residuals(pims, R_body, bias0, bg - e).reshape(-1)) / (2 * h)
        bg = bg + np.linalg.lstsq(J, -r, rcond=None)[0]
    r = _rotation_residuals(pims, R_body, bias0, bg)
    return bg, float(np.sqrt(np.mean(np.sum(r**2, axis=1))))


def _tangent_basis(g: np.ndarray) -> np.ndarray:
    """(3,2) orthonormal basis of the plane perpendicular to g."""
    a = g / np.linalg.norm(g)
    tmp = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    b1 = np.cross(a, tmp)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(a, b1)], axis=1)


def _accel_bias_jacobians(pim: gtsam.PreintegratedCombinedMeasurements, bias: gtsam.imuBias.ConstantBias,
                          h: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(dΔp/db_a, dΔv/db_a), each (3,3), by central differences of gtsam's (linear) bias correction."""
    Jp, Jv = np.empty((3, 3)), np.empty((3, 3))
    ba, bg = np.asarray(bias.accelerometer()), np.asarray(bias.gyroscope())
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        plus, minus = _deltas(pim, make_bias(ba + e, bg)), _deltas(pim, make_bias(ba - e, bg))
        Jp[:, a] = (plus[1] - minus[1]) / (2 * h)
        Jv[:, a] = (plus[2] - minus[2]) / (2 * h)
    return Jp, Jv


def _linear_system(c: np.ndarray, R_cam: np.ndarray, t_cb: np.ndarray, R_body: np.ndarray,
                   deltas: list[tuple[np.ndarray, ...]], covs: list[np.ndarray],
                   jacs: list[tuple[np.ndarray, np.ndarray]] | None) -> tuple[np.ndarray, np.ndarray]:
    """Whitened A x = b, x = [v_0..v_{K-1} (3K), g (3), s (1)(, δb_a (3))], visual frame (VINS-Mono eq. 13).

    p_body_k = s c_k + R_cam_k t_cb (t_cb metric: body origin in the camera frame). Each keyframe
    pair's 6 rows are whitened by the pim's (Δp, Δv) covariance ``covs[k]`` (6,6), so long and
    short intervals weigh what the IMU noise says; ``jacs`` adds the accel-bias change δb_a.
    """
    K = len(c)
    n = 3 * K + 4 + (3 if jacs is not None else 0)
    A = np.zeros((6 * (K - 1), n))
    b = np.zeros(6 * (K - 1))
    I3 = np.eye(3)
    for k, (_, dp, dv, dt, _) in enumerate(deltas):
        r = 6 * k
        # position: s (c_j - c_i) - v_i dt - 0.5 g dt^2 = R_bi Δp - (R_cj - R_ci) t_cb
        A[r : r + 3, 3 * k : 3 * k + 3] = -dt * I3
        A[r : r + 3, 3 * K : 3 * K + 3] = -0.5 * dt**2 * I3
        A[r : r + 3, 3 * K + 3] = c[k + 1] - c[k]
        b[r : r + 3] = R_body[k] @ dp - (R_cam[k + 1] - R_cam[k]) @ t_cb
        # velocity: v_j - v_i - g dt = R_bi Δv
        A[r + 3 : r + 6, 3 * k : 3 * k + 3] = -I3
        A[r + 3 : r + 6, 3 * k + 3 : 3 * k + 6] = I3
        A[r + 3 : r + 6, 3 * K : 3 * K + 3] = -dt * I3
        b[r + 3 : r + 6] = R_body[k] @ dv
        if jacs is not None:  # Δ(b_a + δ) = Δ + J δ moves to the left-hand side
            A[r : r + 3, 3 * K + 4 :] = -R_body[k] @ jacs[k][0]
            A[r + 3 : r + 6, 3 * K + 4 :] = -R_body[k] @ jacs[k][1]
        Rk = np.kron(np.eye(2), R_body[k])
        L = np.linalg.cholesky(Rk @ covs[k] @ Rk.T)
        A[r : r + 6] = np.linalg.solve(L, A[r : r + 6])
        b[r : r + 6] = np.linalg.solve(L, b[r : r + 6])
    return A, b


def _refine_gravity(A: np.ndarray, b: np.ndarray, g0: np.ndarray, gravity: float, K: int,
                    iterations: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Gravity on the sphere |g| = gravity (VINS-Mono RefineGravity): (x, g (3), whitened residual rms)."""
    g = gravity * g0 / np.linalg.norm(g0)
    gi = np.arange(3 * K, 3 * K + 3)
    rest = np.setdiff1d(np.arange(A.shape[1]), gi)
    x = np.zeros(A.shape[1])
    for _ in range(iterations):
        B = _tangent_basis(g)
        sol = np.linalg.lstsq(np.hstack([A[:, rest], A[:, gi] @ B]), b - A[:, gi] @ g, rcond=None)[0]
        g = g + B @ sol[len(rest):]
        g = gravity * g / np.linalg.norm(g)
        x[rest] = sol[: len(rest)]
    x[gi] = g
    return x, g, float(np.sqrt(np.mean((A @ x - b) ** 2)))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation R (3,3) with R a/|a| = b/|b|."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, cth = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if cth > 0:
            return np.eye(3)
        perp = _tangent_basis(a)[:, 0]
        return so3_exp(np.pi * perp)
    return so3_exp(axis / s * np.arctan2(s, cth))


def spaced_subset(times: np.ndarray, min_dt: float) -> np.ndarray:
    """Indices of a time-ordered subset, consecutive ones >= min_dt apart, from the first to the last."""
    sel = [0]
    for i in range(1, len(times)):
        if times[i] - times[sel[-1]] >= min_dt:
            sel.append(i)
    if sel[-1] != len(times) - 1:  # end on the newest keyframe; the gap before it only grows
        if len(sel) > 1:
            sel[-1] = len(times) - 1
        else:
            sel.append(len(times) - 1)
    return np.array(sel)


def _propagate_velocities(al: ViAlignment, sel: np.ndarray, times: np.ndarray, T_wc: np.ndarray, T_body_cam: np.ndarray,
                          imu: ImuSamples, params: gtsam.PreintegrationCombinedParams, gravity: float) -> ViAlignment:
    """``al`` solved on keyframes ``sel``: velocities (world) of all keyframes, each from the previous solved one
    by v_k = v_i + g (t_k - t_i) + R_wb_i Δv_ik (the body attitude from vision, rotated to the world)."""
    R_body = T_wc[:, :3, :3] @ np.linalg.inv(np.asarray(T_body_cam, dtype=np.float64))[:3, :3]
    bias = make_bias(al.accel_bias, al.gyro_bias)
    g_w = np.array([0.0, 0.0, -gravity])
    vel = np.empty((len(times), 3))
    vel[sel] = al.velocities
    prev = 0
    for k in range(len(times)):
        if k in sel:
            prev = int(np.flatnonzero(sel == k)[0])
            continue
        i = int(sel[prev])
        dv = _deltas(preintegrate(imu, times[i], times[k], params, bias), bias)[2]
        vel[k] = al.velocities[prev] + g_w * (times[k] - times[i]) + al.R_world_visual @ R_body[i] @ dv
    return dataclasses.replace(al, velocities=vel)


def vi_align(
    times: np.ndarray,
    T_world_cam: np.ndarray,
    T_body_cam: np.ndarray,
    pims: Seq[gtsam.PreintegratedCombinedMeasurements] | None = None,
    imu: ImuSamples | None = None,
    params: gtsam.PreintegrationCombinedParams | None = None,
    accel_bias: np.ndarray | None = None,
    gyro_bias: np.ndarray | None = None,
    gravity: float = 9.81,
    refine_iterations: int = 4,
    accel_bias_sigma: float | None = 0.1,
    accel_bias_min_span_s: float = 3.0,
    min_dt_s: float = 0.0,
) -> ViAlignment:
    """Align K up-to-scale keyframe poses with the IMU (see module doc).

    times: (K,) s, IMU clock. T_world_cam: (K,4,4) visual-SLAM poses of the
    camera, up to scale, in an arbitrary (visual) world frame. T_body_cam: (4,4)
    metric extrinsic. Either ``pims`` (K-1 consecutive windows, all linearised
    at the same bias) or ``imu`` + ``params`` (then the windows are
    preintegrated here, and again after the gyro-bias fit). accel_bias /
    gyro_bias: (3,) starting biases (zeros when None). accel_bias_sigma: prior
    sigma (m/s^2) of the accelerometer-bias change estimated with scale and
    gravity (ORB-SLAM3 estimates it too; VINS-Mono does not); None holds it fixed,
    and so does a keyframe span shorter than ``accel_bias_min_span_s``: on
    EuRoC, holding the bias fixed costs gravity and scale accuracy, and
    estimating it over short spans lets it trade with gravity (docs/inertial.md,
    "Visual-inertial alignment").

    min_dt_s (with ``imu``): solve on a subset of keyframes at least this far apart and give the others
    velocities by IMU propagation from the previous solved one. Why: scale multiplies the visual positions,
    which carry noise the rows do not model, so least squares shrinks it (errors in variables); the
    preintegrated Δp grows with dt^2 while that noise does not (measured on the synthetic room:
    docs/inertial.md, "Visual-inertial alignment").
    """
    times = np.asarray(times, dtype=np.float64)
    T_wc = np.asarray(T_world_cam, dtype=np.float64)
    K = len(times)
    if K < MIN_KEYFRAMES or T_wc.shape != (K, 4, 4):
        raise InertialError(f"vi_align needs >= {MIN_KEYFRAMES} keyframes with (K,4,4) poses; got {K} times, poses {T_wc.shape}")
    if min_dt_s > 0 and imu is not None and params is not None and np.min(np.diff(times)) < min_dt_s:
        sel = spaced_subset(times, min_dt_s)
        if len(sel) < MIN_KEYFRAMES:
            raise InertialError(f"vi_align: only {len(sel)} keyframes are {min_dt_s} s apart; need {MIN_KEYFRAMES}")
        al = vi_align(times[sel], T_wc[sel], T_body_cam, imu=imu, params=params, accel_bias=accel_bias,
                      gyro_bias=gyro_bias, gravity=gravity, refine_iterations=refine_iterations,
                      accel_bias_sigma=accel_bias_sigma, accel_bias_min_span_s=accel_bias_min_span_s)
        return _propagate_velocities(al, sel, times, T_wc, T_body_cam, imu, params, gravity)
    bias0 = make_bias(accel_bias, gyro_bias)
    if pims is None:
        if imu is None or params is None:
            raise InertialError("vi_align needs either pims or imu + params")
        pims = [preintegrate(imu, times[k], times[k + 1], params, bias0) for k in range(K - 1)]
    elif len(pims) != K - 1:
        raise InertialError(f"vi_align got {len(pims)} pims for {K} keyframes; need K-1 = {K - 1}")
    else:
        bias0 = pims[0].biasHat()

    T_cb = np.linalg.inv(np.asarray(T_body_cam, dtype=np.float64))
    R_cam = T_wc[:, :3, :3]
    R_body = R_cam @ T_cb[:3, :3]
    bg, rot_rms = estimate_gyro_bias(pims, R_body, bias0)
    bias = _with_gyro(bias0, bg)
    if imu is not None and params is not None:  # relinearise at the new bias rather than rely on first order
        pims = [preintegrate(imu, times[k], times[k + 1], params, bias) for k in range(K - 1)]
    deltas = [_deltas(p, bias) for p in pims]
    covs = [np.asarray(p.preintMeasCov())[3:9, 3:9] for p in pims]  # gtsam order: rot, pos, vel, b_a, b_g
    with_ba = accel_bias_sigma is not None and times[-1] - times[0] >= accel_bias_min_span_s
    jacs = [_accel_bias_jacobians(p, bias) for p in pims] if with_ba else None

    A, b = _linear_system(T_wc[:, :3, 3], R_cam, T_cb[:3, 3], R_body, deltas, covs, jacs)
    if jacs is not None and accel_bias_sigma is not None:  # prior rows: δb_a ~ N(0, sigma^2), in the same whitened units
        A = np.vstack([A, np.hstack([np.zeros((3, 3 * K + 4)), np.eye(3) / accel_bias_sigma])])
        b = np.concatenate([b, np.zeros(3)])
    # First solve without the accel bias: it is nearly parallel to gravity until g is pinned to the sphere.
    x0 = np.linalg.lstsq(A[:, : 3 * K + 4], b, rcond=None)[0]
    g_init = x0[3 * K : 3 * K + 3]
    if not np.all(np.isfinite(x0)) or np.linalg.norm(g_init) < 1e-6:
        raise InertialError("vi_align: the linear system is degenerate (too little motion or rotation between keyframes)")
    x, g, res = _refine_gravity(A, b, g_init, gravity, K, refine_iterations)
    scale = float(x[3 * K + 3])
    if not scale > 0:
        raise InertialError(f"vi_align: estimated scale {scale:.4g} is not positive (too little acceleration to observe scale)")
    R_wv = rotation_between(g, np.array([0.0, 0.0, -1.0]))
    vel = x[: 3 * K].reshape(K, 3) @ R_wv.T
    ba = np.asarray(bias.accelerometer()) + (x[3 * K + 4 :] if jacs is not None else 0.0)
    return ViAlignment(scale, R_wv, vel, bg, g, rot_rms, res, ba)
