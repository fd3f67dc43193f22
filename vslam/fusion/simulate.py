"""Simulated ground vehicle, strapdown IMU, GNSS constellation and a drifting VO track.

Frames and units (seed 000 eq. 6 ordering): the navigation frame is a local level frame
with axes (North, Up, East), metres; the body frame is (forward, up, right). Gravity is
constant (flat Earth over a few km, a few minutes). ``C`` is C_b^n, body -> navigation.

The truth is produced by the *same* discrete mechanisation (``mechanize_step``) fed with
the true specific force and angular rate, so the only INS errors are the simulated sensor
errors (biases, noise) and initial errors, not integration-scheme mismatch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from vslam.geometry.se3 import so3_exp, so3_log

G_N = np.array([0.0, -9.80665, 0.0])  # gravity in (N, U, E), m/s^2


def mechanize_step(p: np.ndarray, v: np.ndarray, C: np.ndarray, f_b: np.ndarray, w_b: np.ndarray,
                   dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One strapdown step: a = C f + g; p += v dt + a dt^2/2; v += a dt; C <- C exp([w dt x])."""
    a = C @ f_b + G_N
    return p + v * dt + 0.5 * a * dt * dt, v + a * dt, C @ so3_exp(w_b * dt)


@dataclass(frozen=True)
class TrajectoryConfig:
    """A car-like drive: constant speed with turns (yaw rate profile), mild up/down slopes."""

    duration_s: float = 300.0
    dt_imu: float = 0.1
    speed_mps: float = 12.0
    turn_period_s: float = 40.0
    max_yaw_rate: float = 0.12
    vertical_amp_mps: float = 0.3


@dataclass(frozen=True)
class Truth:
    """t (T,), p (T, 3) m, v (T, 3) m/s, C (T, 3, 3); IMU inputs f_b, w_b (T, 3) at t[k] -> t[k+1]."""

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    C: np.ndarray
    f_b: np.ndarray
    w_b: np.ndarray


def simulate_truth(cfg: TrajectoryConfig) -> Truth:
    """Yaw-rate and speed profile -> true IMU inputs -> truth by mechanisation."""
    n = int(round(cfg.duration_s / cfg.dt_imu))
    t = np.arange(n + 1) * cfg.dt_imu
    yaw_rate = cfg.max_yaw_rate * np.sin(2 * np.pi * t / cfg.turn_period_s) ** 3
    vz = cfg.vertical_amp_mps * np.sin(2 * np.pi * t / (1.7 * cfg.turn_period_s))
    p, v, C = np.zeros(3), np.array([cfg.speed_mps, vz[0], 0.0]), np.eye(3)
    P, V, Cs, F, W = [p], [v], [C], [], []
    for k in range(n):
        # acceleration that turns the velocity with the heading at constant speed, plus the climb profile
        w_b = np.array([0.0, yaw_rate[k], 0.0])
        C_next = C @ so3_exp(w_b * cfg.dt_imu)
        fwd_n = C_next[:, 0]
        v_next = np.array([fwd_n[0], 0.0, fwd_n[2]]) * cfg.speed_mps
        v_next[1] = vz[k + 1]
        a = (v_next - v) / cfg.dt_imu
        f_b = C.T @ (a - G_N)
        p, v, C = mechanize_step(p, v, C, f_b, w_b, cfg.dt_imu)
        P.append(p), V.append(v), Cs.append(C), F.append(f_b), W.append(w_b)
    return Truth(t, np.array(P), np.array(V), np.array(Cs), np.array(F), np.array(W))


def truth_from_samples(t: np.ndarray, p: np.ndarray, C: np.ndarray, dt: float) -> Truth:
    """An external trajectory -> ``Truth`` at the IMU rate, with the IMU inputs that reproduce it.

    t (K,) s increasing; p (K, 3) navigation-frame positions, m; C (K, 3, 3) C_b^n. Positions are
    interpolated by a cubic spline (velocity = its derivative), attitudes by slerp, on t - t[0] in steps
    of dt; f_b and w_b are the finite differences that ``mechanize_step`` integrates back, and the truth
    is that integration (so the INS sees no model mismatch, as with ``simulate_truth``). It stays within
    millimetres of the spline at dt = 0.01 s.
    """
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    t = np.asarray(t, dtype=np.float64) - float(t[0])
    if len(t) < 4 or np.any(np.diff(t) <= 0):
        raise ValueError("an external trajectory needs >= 4 samples with increasing time")
    ti = np.arange(int(np.floor(t[-1] / dt)) + 1) * dt
    spline = CubicSpline(t, np.asarray(p, dtype=np.float64), axis=0)
    v_ref = spline(ti, 1)
    Cs = Slerp(t, Rotation.from_matrix(np.asarray(C, dtype=np.float64)))(ti).as_matrix()
    pk, vk, Ck = spline(ti[0]), v_ref[0], Cs[0]
    P, V, Cl, F, W = [pk], [vk], [Ck], [], []
    for k in range(len(ti) - 1):
        w_b = so3_log(Ck.T @ Cs[k + 1]) / dt  # lands exactly on the next sampled attitude
        f_b = Ck.T @ ((v_ref[k + 1] - vk) / dt - G_N)  # lands exactly on the next spline velocity
        pk, vk, Ck = mechanize_step(pk, vk, Ck, f_b, w_b, dt)
        P.append(pk), V.append(vk), Cl.append(Ck), F.append(f_b), W.append(w_b)
    return Truth(ti, np.array(P), np.array(V), np.array(Cl), np.array(F), np.array(W))


@dataclass(frozen=True)
class ImuConfig:
    """Tactical/MEMS-grade errors: constant bias (1-sigma), white noise density, bias random walk."""

    accel_bias: float = 0.05  # m/s^2
    gyro_bias: float = 2e-4  # rad/s (~40 deg/h)
    accel_noise: float = 0.02  # m/s^2/sqrt(Hz) -> per-sample sigma = noise / sqrt(dt)
    gyro_noise: float = 2e-4  # rad/s/sqrt(Hz)
    accel_bias_rw: float = 1e-4
    gyro_bias_rw: float = 1e-6


def simulate_imu(truth: Truth, cfg: ImuConfig, dt: float, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Measured (f_b, w_b) (T, 3) = truth + bias(t) + white noise; also returns the bias histories."""
    n = len(truth.f_b)
    ba = cfg.accel_bias * rng.standard_normal(3) + np.cumsum(cfg.accel_bias_rw * np.sqrt(dt) * rng.standard_normal((n, 3)), 0)
    bg = cfg.gyro_bias * rng.standard_normal(3) + np.cumsum(cfg.gyro_bias_rw * np.sqrt(dt) * rng.standard_normal((n, 3)), 0)
    f = truth.f_b + ba + cfg.accel_noise / np.sqrt(dt) * rng.standard_normal((n, 3))
    w = truth.w_b + bg + cfg.gyro_noise / np.sqrt(dt) * rng.standard_normal((n, 3))
    return f, w, ba, bg


@dataclass(frozen=True)
class GnssConfig:
    """Constellation, receiver clock and the error model of the pseudoranges.

    noise: 'gaussian'; 'mixture' = (1-eps) N(0, s^2) + eps N(0, (kappa s)^2); 'student' = t(nu) * s.
    multipath_prob: per satellite and epoch, a positive pseudorange bias U(20, 120) m and a
        rate error N(0, 2 m/s) (reflected signal: longer path, wrong Doppler).
    outages: (t_start, t_end, satellites kept); kept = 0 is a bridge/tunnel, 2-3 an urban canyon
        (the highest-elevation satellites survive).
    """

    n_sats: int = 8
    rate_hz: float = 1.0
    sigma_pr: float = 3.0
    sigma_prr: float = 0.1
    noise: Literal["gaussian", "mixture", "student"] = "mixture"
    mix_eps: float = 0.1
    mix_kappa: float = 8.0
    student_nu: float = 3.0
    multipath_prob: float = 0.05
    clock_drift_sigma: float = 0.05  # m/s/sqrt(s), random walk of the clock drift
    outages: tuple[tuple[float, float, int], ...] = ((100.0, 130.0, 3), (200.0, 215.0, 0))


@dataclass(frozen=True)
class GnssData:
    """sats (S, 3) positions m; elev (S,); per epoch: t (E,), pr / prr (E, S) with NaN when not visible;
    clock bias / drift (E,) truth; is_outlier (E, S) bool."""

    sats: np.ndarray
    elev: np.ndarray
    t: np.ndarray
    pr: np.ndarray
    prr: np.ndarray
    clk: np.ndarray
    drift: np.ndarray
    is_outlier: np.ndarray


def _heavy_noise(cfg: GnssConfig, shape: tuple[int, ...], sigma: float, rng: np.random.Generator) -> np.ndarray:
    if cfg.noise == "gaussian":
        return sigma * rng.standard_normal(shape)
    if cfg.noise == "mixture":
        s = np.where(rng.random(shape) < cfg.mix_eps, cfg.mix_kappa * sigma, sigma)
        return s * rng.standard_normal(shape)
    return sigma * rng.standard_t(cfg.student_nu, shape)


def simulate_gnss(truth: Truth, cfg: GnssConfig, rng: np.random.Generator) -> GnssData:
    """Static satellites 22 000 km away (az/el random, el 15-85 deg), pseudorange and rate."""
    az = rng.uniform(0, 2 * np.pi, cfg.n_sats)
    el = np.deg2rad(rng.uniform(15, 85, cfg.n_sats))
    dirs = np.stack([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)], 1)
    sats = 2.2e7 * dirs
    step = int(round(1.0 / (cfg.rate_hz * (truth.t[1] - truth.t[0]))))
    idx = np.arange(step, len(truth.t), step)
    t = truth.t[idx]
    drift = 0.5 + np.cumsum(cfg.clock_drift_sigma * np.sqrt(1 / cfg.rate_hz) * rng.standard_normal(len(t)))
    clk = 100.0 + np.cumsum(drift / cfg.rate_hz)
    d = sats[None] - truth.p[idx][:, None]  # (E, S, 3)
    r = np.linalg.norm(d, axis=2)
    e = d / r[..., None]
    pr = r + clk[:, None] + _heavy_noise(cfg, r.shape, cfg.sigma_pr, rng)
    prr = -np.einsum("esk,ek->es", e, truth.v[idx]) + drift[:, None] + _heavy_noise(cfg, r.shape, cfg.sigma_prr, rng)
    out = rng.random(r.shape) < cfg.multipath_prob
    pr[out] += rng.uniform(20, 120, out.sum())
    prr[out] += 2.0 * rng.standard_normal(out.sum())
    order = np.argsort(-el)
    for t0, t1, keep in cfg.outages:
        rows = (t >= t0) & (t < t1)
        hidden = order[keep:]
        pr[np.ix_(rows, hidden)] = np.nan
        prr[np.ix_(rows, hidden)] = np.nan
    return GnssData(sats, el, t, pr, prr, clk, drift, out & ~np.isnan(pr))


def drifting_vo_track(t: np.ndarray, p_true: np.ndarray, rng: np.random.Generator, drift_per_m: float = 0.01,
                      noise_m: float = 0.05) -> np.ndarray:
    """Synthetic visual-odometry positions (T, 3): truth + random-walk drift proportional to distance.

    Stands in for a real vslam trajectory (same (timestamps, positions) interface).
    """
    step = np.linalg.norm(np.diff(p_true, axis=0), axis=1)
    drift = np.cumsum(drift_per_m * step[:, None] * rng.standard_normal((len(step), 3)), axis=0)
    drift = np.vstack([np.zeros(3), drift])
    bias_dir = rng.standard_normal(3)
    bias = 0.5 * drift_per_m * np.cumsum(np.r_[0.0, step])[:, None] * bias_dir / np.linalg.norm(bias_dir)
    return p_true + drift + bias + noise_m * rng.standard_normal(p_true.shape)
