"""How well IMU preintegration predicts the real motion (docs/inertial.md).

From ground-truth states (pose, velocity, biases) at the start of each window,
preintegrate the recorded IMU over 0.5 / 1 / 2 s and compare the predicted
pose with the ground truth at the window end. The error is the residual of
gtsam's CombinedImuFactor (rotation Log(R_pred^T R_gt), position in the start
body frame) and NEES uses the pim's own covariance (``preintMeasCov``,
rotation + position block, 6 dof), so NEES ≈ 6 means the noise model explains
the error. The static-window numbers compare ``static_init`` with the ground
truth attitude and gyro bias.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vslam.data.euroc import BodyGroundTruth, EurocSequence
from vslam.data.types import ImuNoise, ImuSamples
from vslam.errors import InertialError
from vslam.geometry.se3 import so3_exp, so3_log
from vslam.inertial.init import static_init, vi_align
from vslam.inertial.preintegration import make_bias, make_params, preintegrate, predict

logger = logging.getLogger(__name__)

CHI2_95_6DOF = 12.592  # 95 % quantile of chi-square with 6 degrees of freedom


@dataclass(frozen=True)
class WindowErrors:
    """Per-window results of one window length; arrays (N,).

    t0: window start (s); pos_err: |p_pred - p_gt| m; rot_err: rotation angle rad;
    nees: 6-dof NEES; nees_rot / nees_pos: 3-dof NEES of each block alone;
    sigma_pos: sqrt(trace) of the predicted position covariance, m.
    """

    length_s: float
    t0: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray
    nees: np.ndarray
    nees_rot: np.ndarray
    nees_pos: np.ndarray
    sigma_pos: np.ndarray

    def summary(self) -> dict[str, float]:
        n = len(self.t0)
        return {
            "length_s": self.length_s,
            "windows": n,
            "pos_rmse_m": float(np.sqrt(np.mean(self.pos_err**2))),
            "pos_median_m": float(np.median(self.pos_err)),
            "rot_rmse_deg": float(np.degrees(np.sqrt(np.mean(self.rot_err**2)))),
            "sigma_pos_median_m": float(np.median(self.sigma_pos)),
            "nees_mean": float(np.mean(self.nees)),
            "nees_median": float(np.median(self.nees)),
            "nees_rot_mean": float(np.mean(self.nees_rot)),
            "nees_pos_mean": float(np.mean(self.nees_pos)),
            "frac_nees_below_chi2_95": float(np.mean(self.nees < CHI2_95_6DOF)),
            # The factor by which every noise density would have to grow for mean NEES = 6.
            "noise_inflation_for_consistency": float(np.sqrt(np.mean(self.nees) / 6.0)),
        }


def _block_nees(e: np.ndarray, C: np.ndarray) -> float:
    return float(e @ np.linalg.solve(C, e))


def _windows(imu: ImuSamples, t: np.ndarray, length_s: float, stride_s: float | None = None) -> list[tuple[int, int]]:
    """(start, end) indices into the ground-truth times ``t`` of windows ``length_s`` long, starting every
    ``stride_s`` (default: back to back), that the IMU covers."""
    period = float(np.median(np.diff(t)))
    steps = max(1, int(round(length_s / period)))
    stride = max(1, int(round((stride_s or length_s) / period)))
    return [(i, i + steps) for i in range(0, len(t) - steps, stride) if t[i] >= imu.t[0] and t[i + steps] <= imu.t[-1]]


def window_errors(
    imu: ImuSamples,
    t: np.ndarray,
    T_world_body: np.ndarray,
    velocity: np.ndarray,
    accel_bias: np.ndarray,
    gyro_bias: np.ndarray,
    noise: ImuNoise,
    length_s: float,
    stride_s: float | None = None,
    gravity: float = 9.81,
) -> WindowErrors:
    """Preintegrate windows of ``length_s`` between ground-truth states and compare with the truth.

    t (M,) s; T_world_body (M,4,4); velocity, accel_bias, gyro_bias (M,3): the
    ground-truth states (any rate; window ends snap to these times). stride_s:
    spacing of window starts (default: ``length_s``, non-overlapping windows).
    Windows the IMU does not cover are skipped.
    """
    params = make_params(noise, gravity)
    rows = []
    for i, j in _windows(imu, t, length_s, stride_s):
        bias = make_bias(accel_bias[i], gyro_bias[i])
        pim = preintegrate(imu, t[i], t[j], params, bias)
        Ri, pi = T_world_body[i, :3, :3], T_world_body[i, :3, 3]
        R, p, _ = predict((Ri, pi, velocity[i]), bias, pim)
        # CombinedImuFactor residual convention: rotation in the end frame, position in the start frame.
        e_rot = so3_log(R.T @ T_world_body[j, :3, :3])
        e_pos = Ri.T @ (T_world_body[j, :3, 3] - p)
        C = pim.preintMeasCov()[:6, :6]  # gtsam order: rotation, position, velocity, accel bias, gyro bias
        e = np.r_[e_rot, e_pos]
        rows.append((t[i], np.linalg.norm(T_world_body[j, :3, 3] - p), np.linalg.norm(e_rot), _block_nees(e, C),
                     _block_nees(e_rot, C[:3, :3]), _block_nees(e_pos, C[3:, 3:]), np.sqrt(np.trace(C[3:, 3:]))))
    if not rows:
        raise InertialError(f"no {length_s} s window lies inside both the IMU and the ground truth")
    a = np.array(rows)
    return WindowErrors(float(length_s), a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5], a[:, 6])


@dataclass(frozen=True)
class WindowResiduals:
    """Residuals of one window length with the pieces their covariance is built from; arrays lead with N.

    e: (N,6) rotation (end frame) + position (start frame) residual, as ``window_errors``.
    C_fixed: (N,6,6) the part no fit changes: bias random walks (sensor.yaml) + integration noise.
    C_gyro / C_accel: (N,6,6) covariance per unit gyro / accel white-noise density^2 (preintMeasCov is linear in
    the noise covariances: the propagation matrices depend on the measurements only).
    J_bias: (N,6,6) d e / d (accel bias, gyro bias) at the ground-truth bias (gtsam's first-order correction).
    """

    length_s: float
    t0: np.ndarray
    e: np.ndarray
    C_fixed: np.ndarray
    C_gyro: np.ndarray
    C_accel: np.ndarray
    J_bias: np.ndarray

    def subset(self, m: np.ndarray) -> WindowResiduals:
        return WindowResiduals(self.length_s, self.t0[m], self.e[m], self.C_fixed[m], self.C_gyro[m],
                               self.C_accel[m], self.J_bias[m])


@dataclass(frozen=True)
class ImuNoiseModel:
    """White-noise densities of the IMU plus the std of the *starting* biases' error (here: of the ground-truth
    biases, themselves an estimator's output), which makes an error grow like t rather than sqrt(t)."""

    gyro_noise_density: float  # rad/s/sqrt(Hz)
    accel_noise_density: float  # m/s^2/sqrt(Hz)
    gyro_bias_sigma: float  # rad/s
    accel_bias_sigma: float  # m/s^2

    def covariance(self, r: WindowResiduals) -> np.ndarray:
        """(N,6,6) predicted covariance of ``r.e``."""
        Sb = np.diag([self.accel_bias_sigma**2] * 3 + [self.gyro_bias_sigma**2] * 3)
        return (r.C_fixed + self.gyro_noise_density**2 * r.C_gyro + self.accel_noise_density**2 * r.C_accel
                + r.J_bias @ Sb @ r.J_bias.transpose(0, 2, 1))


def window_residuals(imu: ImuSamples, t: np.ndarray, T_world_body: np.ndarray, velocity: np.ndarray,
                     accel_bias: np.ndarray, gyro_bias: np.ndarray, noise: ImuNoise, length_s: float,
                     gravity: float = 9.81) -> WindowResiduals:
    """Non-overlapping windows of ``length_s`` between ground-truth states (as ``window_errors``), with the
    covariance split into its linear pieces so that a noise model can be fitted without re-integrating."""
    p_fixed = make_params(ImuNoise(0.0, noise.gyro_random_walk, 0.0, noise.accel_random_walk, noise.rate_hz), gravity)
    p_gyro = make_params(ImuNoise(1.0, 0.0, 0.0, 0.0, noise.rate_hz), gravity, integration_sigma=0.0)
    p_accel = make_params(ImuNoise(0.0, 0.0, 1.0, 0.0, noise.rate_hz), gravity, integration_sigma=0.0)
    rows: list[tuple] = []
    for i, j in _windows(imu, t, length_s):
        Ri, pi, vi = T_world_body[i, :3, :3], T_world_body[i, :3, 3], velocity[i]

        def resid(ba: np.ndarray, bg: np.ndarray, pim) -> np.ndarray:
            R, p, _ = predict((Ri, pi, vi), make_bias(ba, bg), pim)
            return np.r_[so3_log(R.T @ T_world_body[j, :3, :3]), Ri.T @ (T_world_body[j, :3, 3] - p)]

        bias = make_bias(accel_bias[i], gyro_bias[i])
        pim = preintegrate(imu, t[i], t[j], p_fixed, bias)
        J = np.empty((6, 6))
        for a in range(6):  # the correction is linear in the bias: central differences are exact
            h = np.zeros(6)
            h[a] = 1e-3 if a < 3 else 1e-4
            J[:, a] = (resid(accel_bias[i] + h[:3], gyro_bias[i] + h[3:], pim)
                       - resid(accel_bias[i] - h[:3], gyro_bias[i] - h[3:], pim)) / (2 * h[a])
        rows.append((t[i], resid(accel_bias[i], gyro_bias[i], pim), pim.preintMeasCov()[:6, :6],
                     preintegrate(imu, t[i], t[j], p_gyro, bias).preintMeasCov()[:6, :6],
                     preintegrate(imu, t[i], t[j], p_accel, bias).preintMeasCov()[:6, :6], J))
    if not rows:
        raise InertialError(f"no {length_s} s window lies inside both the IMU and the ground truth")
    return WindowResiduals(float(length_s), *(np.array([r[k] for r in rows]) for k in range(6)))


def nees(r: WindowResiduals, model: ImuNoiseModel) -> np.ndarray:
    """(N,) 6-dof NEES of each window under ``model``."""
    C = model.covariance(r)
    return np.einsum("ni,ni->n", r.e, np.linalg.solve(C, r.e[..., None])[..., 0])


def fit_noise_model(sets: list[WindowResiduals], start: ImuNoiseModel, fit_bias: bool = True) -> ImuNoiseModel:
    """Maximum-likelihood noise model (Gaussian residuals) over windows of several lengths.

    Several lengths are what separates the four parameters: white noise grows the error like sqrt(t), a
    starting-bias error like t. Nelder-Mead on the log-parameters from ``start``: deterministic.
    fit_bias=False keeps ``start``'s bias sigmas (the "inflate the densities" practice, for comparison).
    """
    from scipy.optimize import minimize

    def model(x: np.ndarray) -> ImuNoiseModel:
        v = np.exp(x)
        return ImuNoiseModel(*v) if fit_bias else ImuNoiseModel(v[0], v[1], start.gyro_bias_sigma, start.accel_bias_sigma)

    def nll(x: np.ndarray) -> float:
        m = model(x)
        total = 0.0
        for r in sets:
            C = m.covariance(r)
            total += float(np.sum(np.einsum("ni,ni->n", r.e, np.linalg.solve(C, r.e[..., None])[..., 0]))
                           + np.sum(np.linalg.slogdet(C)[1]))
        return 0.5 * total

    x = np.log([start.gyro_noise_density, start.accel_noise_density] +
               ([start.gyro_bias_sigma, start.accel_bias_sigma] if fit_bias else []))
    best = np.inf
    for _ in range(5):  # Nelder-Mead stalls on this ridge (white noise vs bias error); restart from its answer
        res = minimize(nll, x, method="Nelder-Mead", options={"maxiter": 2000, "xatol": 1e-5, "fatol": 1e-6})
        x = res.x
        if best - res.fun < 1e-6:
            break
        best = res.fun
    return model(x)


def identified_noise_numbers(imu: ImuSamples, gt: BodyGroundTruth, noise: ImuNoise,
                             lengths: tuple[float, ...] = (0.5, 1.0, 2.0)) -> dict[str, object]:
    """Fit ``ImuNoiseModel`` on the windows that start in the first half of the record, report NEES on the
    second half (held out) per window length, and the fitted values against sensor.yaml."""
    arrays = ground_truth_arrays(gt)
    sets = [window_residuals(imu, *arrays, noise=noise, length_s=L) for L in lengths]
    t_mid = 0.5 * (max(float(arrays[0][0]), float(imu.t[0])) + min(float(arrays[0][-1]), float(imu.t[-1])))
    train = [r.subset(r.t0 < t_mid) for r in sets]
    test = [r.subset(r.t0 >= t_mid) for r in sets]
    start = ImuNoiseModel(noise.gyro_noise_density, noise.accel_noise_density, 1e-3, 1e-2)
    model = fit_noise_model(train, start)
    white = fit_noise_model(train, ImuNoiseModel(noise.gyro_noise_density, noise.accel_noise_density, 0.0, 0.0), fit_bias=False)
    rows = []
    for r in test:
        n, C = nees(r, model), model.covariance(r)
        n_rot = np.einsum("ni,ni->n", r.e[:, :3], np.linalg.solve(C[:, :3, :3], r.e[:, :3, None])[..., 0])
        n_pos = np.einsum("ni,ni->n", r.e[:, 3:], np.linalg.solve(C[:, 3:, 3:], r.e[:, 3:, None])[..., 0])
        rows.append({"length_s": r.length_s, "windows": len(n), "nees_mean": float(np.mean(n)),
                     "nees_median": float(np.median(n)), "nees_rot_mean": float(np.mean(n_rot)),
                     "nees_pos_mean": float(np.mean(n_pos)), "frac_nees_below_chi2_95": float(np.mean(n < CHI2_95_6DOF)),
                     "nees_mean_white_only": float(np.mean(nees(r, white)))})
    return {"model": asdict(model), "train_windows": int(sum(len(r.t0) for r in train)), "split_t": t_mid,
            "gyro_density_x_datasheet": model.gyro_noise_density / noise.gyro_noise_density,
            "accel_density_x_datasheet": model.accel_noise_density / noise.accel_noise_density, "held_out": rows,
            "white_only_x_datasheet": [white.gyro_noise_density / noise.gyro_noise_density,
                                       white.accel_noise_density / noise.accel_noise_density]}


def ground_truth_arrays(gt: BodyGroundTruth) -> tuple[np.ndarray, ...]:
    """(t, T_world_body, velocity, accel_bias, gyro_bias) of EuRoC ground truth; InertialError if it lacks them."""
    if gt.velocity is None or gt.accel_bias is None or gt.gyro_bias is None:
        raise InertialError("ground truth has no velocity/bias columns (EuRoC state_groundtruth_estimate0 needed)")
    return gt.trajectory.timestamps, gt.trajectory.poses, gt.velocity, gt.accel_bias, gt.gyro_bias


def static_window_numbers(imu: ImuSamples, gt: BodyGroundTruth, window_s: float, gravity: float = 9.81) -> dict[str, float]:
    """static_init over the first ``window_s`` seconds of ground truth vs the ground-truth attitude and bias."""
    t, T, _, ba, bg = ground_truth_arrays(gt)
    t0 = max(float(t[0]), float(imu.t[0]))
    t1 = t0 + window_s
    init = static_init(imu, t0, t1, gravity)
    m = (t >= t0) & (t <= t1)
    up_gt = np.mean(T[m, 2, :3], axis=0)  # world +z in the body frame = third row of R_world_body
    up_gt /= np.linalg.norm(up_gt)
    angle = np.degrees(np.arccos(np.clip(init.up_body @ up_gt, -1.0, 1.0)))
    # The same with the ground-truth accel bias as prior: separates the part no still window can observe.
    with_prior = static_init(imu, t0, t1, gravity, accel_bias_prior=np.mean(ba[m], axis=0))
    angle_gt_bias = np.degrees(np.arccos(np.clip(with_prior.up_body @ up_gt, -1.0, 1.0)))
    bg_gt = np.mean(bg[m], axis=0)
    return {
        "window_s": window_s,
        "still": bool(init.still),
        "gravity_dir_err_deg": float(angle),
        "gravity_dir_err_gt_accel_bias_deg": float(angle_gt_bias),
        "gyro_bias_err_rad_s": float(np.linalg.norm(init.gyro_bias - bg_gt)),
        "gyro_bias_gt_norm_rad_s": float(np.linalg.norm(bg_gt)),
        "gyro_bias_err_per_axis": [float(x) for x in init.gyro_bias - bg_gt],
        "force_norm_error": init.force_norm_error,
    }


def alignment_numbers(imu: ImuSamples, gt: BodyGroundTruth, T_body_cam: np.ndarray, noise: ImuNoise,
                      span_s: float = 5.0, keyframe_dt: float = 0.25, stride_s: float = 10.0,
                      skip_s: float = 5.0, gravity: float = 9.81) -> dict[str, float]:
    """vi_align on ground-truth camera poses hidden behind a known similarity (scale 3.7, a tilted frame).

    Stands in for perfect up-to-scale visual SLAM: what the real IMU alone
    allows for scale and gravity. Windows of ``span_s`` start every
    ``stride_s`` after the first ``skip_s`` (the pre-takeoff rest), keyframes
    every ``keyframe_dt``; zero starting biases (nothing taken from the truth).
    """
    t, T, _, _, bg = ground_truth_arrays(gt)
    R_vis, s_true = so3_exp(np.array([0.4, -0.9, 0.3])), 3.7
    params = make_params(noise, gravity)
    period = float(np.median(np.diff(t)))
    step, n_kf = max(1, int(round(keyframe_dt / period))), int(round(span_s / keyframe_dt)) + 1
    scale_err, grav_err, bg_err = [], [], []
    i = int(np.searchsorted(t, t[0] + skip_s))
    while i + step * (n_kf - 1) < len(t) and t[i + step * (n_kf - 1)] <= imu.t[-1]:
        idx = i + step * np.arange(n_kf)
        T_wc = T[idx] @ T_body_cam
        T_vc = T_wc.copy()
        T_vc[:, :3, :3] = R_vis @ T_wc[:, :3, :3]
        T_vc[:, :3, 3] = T_wc[:, :3, 3] @ R_vis.T / s_true
        al = vi_align(t[idx], T_vc, T_body_cam, imu=imu, params=params, gravity=gravity)
        up = al.R_world_visual @ R_vis @ np.array([0.0, 0.0, 1.0])
        scale_err.append(abs(al.scale / s_true - 1.0))
        grav_err.append(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
        bg_err.append(np.linalg.norm(al.gyro_bias - bg[idx].mean(axis=0)))
        i += max(1, int(round(stride_s / period)))
    if not scale_err:
        raise InertialError(f"no {span_s} s alignment window inside the ground truth after {skip_s} s")
    return {"span_s": span_s, "windows": len(scale_err),
            "scale_err_median_pct": 100 * float(np.median(scale_err)), "scale_err_max_pct": 100 * float(np.max(scale_err)),
            "gravity_err_median_deg": float(np.median(grav_err)), "gravity_err_max_deg": float(np.max(grav_err)),
            "gyro_bias_err_median_rad_s": float(np.median(bg_err))}


def evaluate_euroc_imu(
    path: str | Path,
    lengths: tuple[float, ...] = (0.5, 1.0, 2.0),
    static_window_s: float = 4.0,
    noise_scale: float = 1.0,
    align_spans: tuple[float, ...] = (3.0, 5.0, 10.0),
) -> dict[str, object]:
    """All issue-8 IMU numbers for an EuRoC sequence folder: per-length window stats, the static window,
    and visual-inertial alignment on ground-truth poses per keyframe span."""
    seq = EurocSequence(path, sensor="mono")
    imu, gt = seq.imu(), seq.groundtruth_body()
    if imu is None or gt is None:
        raise InertialError(f"{path}: needs imu0/ and state_groundtruth_estimate0/")
    base = seq.calibration.imu or ImuNoise()
    noise = ImuNoise(base.gyro_noise_density * noise_scale, base.gyro_random_walk * noise_scale,
                     base.accel_noise_density * noise_scale, base.accel_random_walk * noise_scale, base.rate_hz)
    arrays = ground_truth_arrays(gt)
    windows = [window_errors(imu, *arrays, noise=noise, length_s=L).summary() for L in lengths]
    return {"sequence": seq.name, "noise": asdict(noise), "noise_scale": noise_scale, "windows": windows,
            "identified": identified_noise_numbers(imu, gt, noise, lengths),
            "static": static_window_numbers(imu, gt, static_window_s),
            "alignment": [alignment_numbers(imu, gt, seq.calibration.T_body_cam0, noise, span_s=s) for s in align_spans]}
