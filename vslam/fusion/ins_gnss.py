"""Tightly coupled INS/GNSS: 15-state INS error model (seed 000 eq. 6) + receiver clock,
pseudorange / pseudorange-rate updates, closed-loop error-state filtering with any filter
of ``filters.FILTERS`` (seed 003 ch. 2 compares EKF, CKF and its adaptive robust SR-CKF).

Error state (17,): dp (3) = p_ins - p, dv (3) = v_ins - v, phi (3) with C_ins = (I + [phi x]) C,
dba (3) = b_a - b_a_hat, dbg (3) = b_g - b_g_hat, dclk (m), ddrift (m/s) = truth - estimate.
Axes (North, Up, East) as in seed 000 eq. 6.

Deviations from seed 000 eq. 6 (noted, on purpose):
- F_INS2 is printed with the velocity *errors* dV_N, dV_H, dV_E where the classical model
  (Salychev) has the velocities V_N, V_H, V_E; we use the velocities.
- the printed F has no specific-force coupling between attitude and velocity error; without
  it roll/pitch/yaw errors are unobservable from GNSS and the filter cannot hold attitude.
  We add -[f^n x] in the (dv, phi) block (``specific_force_coupling=True``).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from vslam.fusion.filters import AdaptiveRobustConfig, Belief, make_filter
from vslam.fusion.simulate import (
    GnssConfig, GnssData, ImuConfig, TrajectoryConfig, Truth, mechanize_step, simulate_gnss, simulate_imu,
    simulate_truth,
)
from vslam.geometry.se3 import skew, so3_exp

log = logging.getLogger(__name__)

EARTH_RATE = 7.2922115e-5  # rad/s, seed 000
A_ELLIPSOID, E2 = 6378245.0, 0.0066934216  # Krasovsky ellipsoid, seed 000 eqs. 7-8
N_ERR = 17


def radii(lat: float) -> tuple[float, float]:
    """R1 meridian, R2 prime-vertical radius of curvature (seed 000 eqs. 7-8)."""
    s2 = np.sin(lat) ** 2
    return A_ELLIPSOID * (1 - E2) * (1 - E2 * s2) ** -1.5, A_ELLIPSOID * (1 - E2 * s2) ** -0.5


def error_model_F(v: np.ndarray, C: np.ndarray, f_n: np.ndarray, lat: float,
                  specific_force_coupling: bool = True) -> np.ndarray:
    """Continuous-time F (17, 17): seed 000 eq. 6 blocks F_INS1..4 plus the clock (b' = d)."""
    vn, vh, ve = v
    R1, R2 = radii(lat)
    u, tg = EARTH_RATE, np.tan(lat)
    F2 = np.array([
        [-vh / R1, -vn / R1, -ve * tg / R2 - 2 * u * np.sin(lat)],
        [-vn * tg / R2, 0.0, ve / R2 - 2 * u * np.cos(lat)],
        [ve * tg / R2 + 2 * u * np.sin(lat), 2 * u * np.cos(lat), vn / R2 - vh / R1],
    ])
    F = np.zeros((N_ERR, N_ERR))
    F[0:3, 3:6] = np.eye(3)  # F_INS1
    F[3:6, 3:6] = F2  # F_INS2
    F[3:6, 9:12] = C  # F_INS3
    F[6:9, 12:15] = C  # F_INS4
    if specific_force_coupling:
        F[3:6, 6:9] = -skew(f_n)
    F[15, 16] = 1.0
    return F


def process_noise(C: np.ndarray, imu: ImuConfig, gnss: GnssConfig, dt: float) -> np.ndarray:
    """Q_d ~ G V V^T G^T dt (seed 000 eq. 6 noise term) + bias and clock random walks."""
    Q = np.zeros((N_ERR, N_ERR))
    Q[3:6, 3:6] = C @ C.T * imu.accel_noise**2 * dt
    Q[6:9, 6:9] = C @ C.T * imu.gyro_noise**2 * dt
    Q[9:12, 9:12] = np.eye(3) * imu.accel_bias_rw**2 * dt
    Q[12:15, 12:15] = np.eye(3) * imu.gyro_bias_rw**2 * dt
    Q[15, 15] = 0.01 * dt
    Q[16, 16] = gnss.clock_drift_sigma**2 * dt
    return Q + 1e-12 * np.eye(N_ERR)


@dataclass
class Nominal:
    """The INS solution the error state is relative to (mutable, local to one run)."""

    p: np.ndarray
    v: np.ndarray
    C: np.ndarray
    ba: np.ndarray
    bg: np.ndarray
    clk: float
    drift: float

    def correct(self, dx: np.ndarray) -> None:
        """Closed-loop feedback of the estimated errors; the error state is then reset to 0."""
        self.p = self.p - dx[0:3]
        self.v = self.v - dx[3:6]
        self.C = so3_exp(-dx[6:9]) @ self.C
        self.ba = self.ba + dx[9:12]
        self.bg = self.bg + dx[12:15]
        self.clk += dx[15]
        self.drift += dx[16]


def gnss_h(nom: Nominal, sats: np.ndarray):
    """Batched h(dx): (N, 17) -> (N, 2S) pseudoranges then rates for the satellites ``sats`` (S, 3)."""

    def h(X: np.ndarray) -> np.ndarray:
        P = nom.p[None] - X[:, 0:3]
        V = nom.v[None] - X[:, 3:6]
        d = sats[None] - P[:, None]  # (N, S, 3)
        r = np.linalg.norm(d, axis=2)
        rate = -np.einsum("nsk,nk->ns", d / r[..., None], V) + (nom.drift + X[:, 16:17])
        return np.hstack([r + nom.clk + X[:, 15:16], rate])

    return h


@dataclass(frozen=True)
class InsGnssConfig:
    """One experiment: trajectory, sensors, filters compared, Monte-Carlo size."""

    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    robust: AdaptiveRobustConfig = field(default_factory=AdaptiveRobustConfig)
    filters: tuple[str, ...] = ("ekf", "ckf", "arsckf")
    runs: int = 10
    latitude_deg: float = 54.2
    init_sigma: tuple[float, float, float, float] = (3.0, 0.2, 0.01, 20.0)  # pos m, vel m/s, att rad, clock m
    skip_s: float = 10.0  # convergence time excluded from the RMS
    specific_force_coupling: bool = True


@dataclass(frozen=True)
class RunResult:
    """Per-epoch output of one filter on one run: t (E,), pos / pos_err / vel_err (E, 3) m, m/s,
    pos_cov (E, 3, 3) filter position covariance, nis (E,) NIS / m, visible (E,) satellites,
    pr_innov (E, S) pseudorange innovation / predicted sigma before the update (NaN if hidden)."""

    t: np.ndarray
    pos: np.ndarray
    pos_err: np.ndarray
    vel_err: np.ndarray
    pos_cov: np.ndarray
    nis: np.ndarray
    visible: np.ndarray
    pr_innov: np.ndarray


def _initial(truth: Truth, gnss: GnssData, cfg: InsGnssConfig, rng: np.random.Generator) -> tuple[Nominal, Belief]:
    sp, sv, sa, sc = cfg.init_sigma
    nom = Nominal(truth.p[0] + sp * rng.standard_normal(3), truth.v[0] + sv * rng.standard_normal(3),
                  so3_exp(sa * rng.standard_normal(3)) @ truth.C[0], np.zeros(3), np.zeros(3),
                  float(gnss.clk[0] - gnss.drift[0] / cfg.gnss.rate_hz + sc * rng.standard_normal()), 0.0)
    sd = np.r_[[sp] * 3, [sv] * 3, [sa] * 3, [cfg.imu.accel_bias] * 3, [cfg.imu.gyro_bias] * 3, sc, 1.0]
    return nom, Belief.from_cov(np.zeros(N_ERR), np.diag(sd**2))


def run_filter(name: str, truth: Truth, imu_f: np.ndarray, imu_w: np.ndarray, gnss: GnssData,
               cfg: InsGnssConfig, rng: np.random.Generator) -> RunResult:
    """Mechanise the measured IMU, predict/update the error state at each GNSS epoch, feed back."""
    filt = make_filter(name, cfg.robust)
    nom, b = _initial(truth, gnss, cfg, rng)
    dt = truth.t[1] - truth.t[0]
    lat = np.deg2rad(cfg.latitude_deg)
    k_imu = 0
    pos, pos_err, vel_err, cov, nis, vis = [], [], [], [], [], []
    innov = np.full(gnss.pr.shape, np.nan)
    for e, t_e in enumerate(gnss.t):
        k_end = int(round(t_e / dt))
        f_sum = np.zeros(3)
        Phi = np.eye(N_ERR)
        for k in range(k_imu, k_end):  # INS mechanisation between epochs
            f_b = imu_f[k] - nom.ba
            f_n = nom.C @ f_b
            F = error_model_F(nom.v, nom.C, f_n, lat, cfg.specific_force_coupling)
            Phi = (np.eye(N_ERR) + F * dt) @ Phi  # first-order transition over one IMU step
            nom.p, nom.v, nom.C = mechanize_step(nom.p, nom.v, nom.C, f_b, imu_w[k] - nom.bg, dt)
            f_sum += f_n
        T = (k_end - k_imu) * dt
        nom.clk += nom.drift * T
        k_imu = k_end
        Q = process_noise(nom.C, cfg.imu, cfg.gnss, T)
        b = filt.predict(b, lambda X, Phi=Phi: X @ Phi.T, Q, F=Phi)
        ok = ~np.isnan(gnss.pr[e])
        if ok.any():
            y = np.r_[gnss.pr[e, ok], gnss.prr[e, ok]]
            R = np.diag(np.r_[[cfg.gnss.sigma_pr**2] * ok.sum(), [cfg.gnss.sigma_prr**2] * ok.sum()])
            b, info = filt.update(b, y, gnss_h(nom, gnss.sats[ok]), R)
            innov[e, ok] = info.v[: ok.sum()] / np.sqrt(np.diag(info.Pyy)[: ok.sum()])
            nom.correct(b.x)
            b = dataclasses.replace(b, x=np.zeros(N_ERR))
            nis.append(info.nis / len(y))
        else:
            nis.append(np.nan)
        pos.append(nom.p.copy())
        cov.append(b.P[0:3, 0:3])
        pos_err.append(nom.p - truth.p[k_end])
        vel_err.append(nom.v - truth.v[k_end])
        vis.append(int(ok.sum()))
    return RunResult(gnss.t.copy(), np.array(pos), np.array(pos_err), np.array(vel_err), np.array(cov),
                     np.array(nis), np.array(vis), innov)


def simulate_run(cfg: InsGnssConfig, rng: np.random.Generator, truth: Truth | None = None):
    """One Monte-Carlo draw of truth, IMU and GNSS (shared by all filters of that run).

    truth: an external trajectory (``simulate.truth_from_samples``, t from 0) instead of cfg.trajectory's drive.
    """
    truth = simulate_truth(cfg.trajectory) if truth is None else truth
    f, w, _, _ = simulate_imu(truth, cfg.imu, float(truth.t[1] - truth.t[0]), rng)
    return truth, f, w, simulate_gnss(truth, cfg.gnss, rng)


def rms(x: np.ndarray) -> float:
    """RMS of the 3-D error norm over rows of x (E, 3)."""
    return float(np.sqrt(np.mean(np.sum(x**2, axis=1))))


def monte_carlo(cfg: InsGnssConfig, seed: int = 0) -> dict[str, dict[str, float]]:
    """RMS position / velocity errors per filter over ``cfg.runs`` seeded runs (same data for every filter).

    Returns {filter: {'pos_rms', 'vel_rms', 'pos_rms_outage', 'per_run_pos': [...]}}.
    """
    rng = np.random.default_rng(seed)
    acc: dict[str, dict[str, list]] = {n: {"pos": [], "vel": [], "pos_out": [], "run": []} for n in cfg.filters}
    for r in range(cfg.runs):
        run_rng = np.random.default_rng(rng.integers(2**63))
        truth, f, w, gnss = simulate_run(cfg, run_rng)
        init_seed = int(run_rng.integers(2**63))
        for name in cfg.filters:
            res = run_filter(name, truth, f, w, gnss, cfg, np.random.default_rng(init_seed))
            keep = res.t >= cfg.skip_s
            degraded = keep & (res.visible < 4)
            acc[name]["pos"].append(res.pos_err[keep])
            acc[name]["vel"].append(res.vel_err[keep])
            acc[name]["pos_out"].append(res.pos_err[degraded])
            acc[name]["run"].append(rms(res.pos_err[keep]))
        log.info("ins_gnss run %d/%d done", r + 1, cfg.runs)
    out = {}
    for name, a in acc.items():
        po = np.vstack(a["pos_out"]) if any(len(x) for x in a["pos_out"]) else np.zeros((1, 3))
        out[name] = {"pos_rms": rms(np.vstack(a["pos"])), "vel_rms": rms(np.vstack(a["vel"])),
                     "pos_rms_degraded": rms(po), "per_run_pos": [float(x) for x in a["run"]]}
    return out


def improvement(base: float, ours: float) -> float:
    """Relative error reduction in percent (positive = ours better)."""
    return 100.0 * (base - ours) / base
