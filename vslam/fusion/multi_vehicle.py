"""Group of M vehicles with own and mutual position/velocity measurements (seed 004).

One axis (the seed treats X, Y, Z separately). State x_p = (x^1..x^M, v^1..v^M);
dynamics x_i = x_{i-1} + v_{i-1} T, v_i = v_{i-1} + a_x T xi (xi ~ N(0, 1)).
Observations: own z^l = x^l + n, mutual z^{kl} = x^k - x^l + n (k != l), same for velocities;
C is the (M^2 x M) matrix stacking them (seed §3).

- Vector KF (seed §3): B = P C_p^T V^-1, P = P_e (E + C_p^T V^-1 C_p P_e)^-1.
- Two-stage (seed §4): static WLS x~ = (C^T V^-1 C)^-1 C^T V^-1 z with covariance
  V_e = (C^T V^-1 C)^-1, then a 2-state KF per vehicle using only the diagonal D^l of V_e
  (cross-correlations B^{kl} ignored, as the seed does).

Both are linear, so we propagate covariances exactly: the vector KF's P is its true error
covariance; for the two-stage we report both its own (optimistic) P and its *true* error
covariance, obtained by propagating the suboptimal gain against the full V_e.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GroupConfig:
    """Seed 004 defaults (fig. 6 case): GPS own sigma 10 m / 3 m/s, SINTELA mutual 1 m, DISS-15 0.4 m/s."""

    M: int = 10
    sigma: float = 10.0  # own position, m
    sigma_v: float = 3.0  # own velocity, m/s
    sigma_mut: float = 1.0  # mutual position, m
    sigma_vmut: float = 0.4  # mutual velocity, m/s
    a_x: float = 0.1  # disturbance, m/s^2
    T: float = 1.0
    steps: int = 100
    use_velocity: bool = True
    p0_pos: float = 100.0  # initial sigma, m
    p0_vel: float = 10.0  # m/s


def observation_matrix(M: int) -> np.ndarray:
    """C (M^2, M): rows ordered (1,1), (1,2)..(1,M), (2,1), (2,2).. as in the seed's z-vector."""
    C = np.zeros((M * M, M))
    for k in range(M):
        for l in range(M):
            r = k * M + l
            C[r, k] += 1.0
            if k != l:
                C[r, l] -= 1.0
    return C


def _noise(M: int, own: float, mut: float) -> np.ndarray:
    d = np.full((M, M), mut**2)
    np.fill_diagonal(d, own**2)
    return np.diag(d.ravel())


def _dynamics(cfg: GroupConfig) -> tuple[np.ndarray, np.ndarray]:
    M, T = cfg.M, cfg.T
    Phi = np.eye(2 * M)
    Phi[:M, M:] = T * np.eye(M)
    Q = np.zeros((2 * M, 2 * M))
    Q[M:, M:] = (cfg.a_x * T) ** 2 * np.eye(M)
    return Phi, Q


def wls(C: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Static fusion A = (C^T V^-1 C)^-1 C^T V^-1 and its error covariance (C^T V^-1 C)^-1 (seed §4)."""
    diag = np.count_nonzero(V - np.diag(np.diag(V))) == 0
    CtVi = C.T / np.diag(V)[None, :] if diag else C.T @ np.linalg.inv(V)  # V is diagonal in the seed
    cov = np.linalg.inv(CtVi @ C)
    return cov @ CtVi, cov


def _measurement(cfg: GroupConfig) -> tuple[np.ndarray, np.ndarray]:
    M = cfg.M
    C = observation_matrix(M)
    if not cfg.use_velocity:
        return np.hstack([C, np.zeros_like(C)]), _noise(M, cfg.sigma, cfg.sigma_mut)
    Cp = np.block([[C, np.zeros_like(C)], [np.zeros_like(C), C]])
    V = np.block([[_noise(M, cfg.sigma, cfg.sigma_mut), np.zeros((M * M, M * M))],
                  [np.zeros((M * M, M * M)), _noise(M, cfg.sigma_v, cfg.sigma_vmut)]])
    return Cp, V


def vector_kf_cov(cfg: GroupConfig) -> np.ndarray:
    """Posterior covariances (steps, 2M, 2M) of the vector KF (seed §3, information form)."""
    Phi, Q = _dynamics(cfg)
    Cp, V = _measurement(cfg)
    info = Cp.T @ np.linalg.solve(V, Cp)
    P = np.diag([cfg.p0_pos**2] * cfg.M + [cfg.p0_vel**2] * cfg.M)
    out = []
    for i in range(cfg.steps):
        Pe = P if i == 0 else Phi @ P @ Phi.T + Q
        P = Pe @ np.linalg.inv(np.eye(2 * cfg.M) + info @ Pe)
        out.append(P)
    return np.array(out)


def two_stage_cov(cfg: GroupConfig) -> tuple[np.ndarray, np.ndarray]:
    """(own P, true error covariance), each (steps, 2M, 2M), of WLS + per-vehicle 2-state KFs (seed §4)."""
    M = cfg.M
    Phi, Q = _dynamics(cfg)
    _, Vx = wls(observation_matrix(M), _noise(M, cfg.sigma, cfg.sigma_mut))
    if cfg.use_velocity:
        _, Vv = wls(observation_matrix(M), _noise(M, cfg.sigma_v, cfg.sigma_vmut))
        Ve = np.block([[Vx, np.zeros((M, M))], [np.zeros((M, M)), Vv]])
        H = np.eye(2 * M)
    else:
        Ve, H = Vx, np.hstack([np.eye(M), np.zeros((M, M))])
    Rd = np.diag(np.diag(Ve))  # the per-vehicle filters see only D^l
    P = np.diag([cfg.p0_pos**2] * M + [cfg.p0_vel**2] * M)
    Pt = P.copy()
    own, true = [], []
    for i in range(cfg.steps):
        Pe = P if i == 0 else Phi @ P @ Phi.T + Q
        Pte = Pt if i == 0 else Phi @ Pt @ Phi.T + Q
        K = Pe @ H.T @ np.linalg.inv(H @ Pe @ H.T + Rd)  # block-diagonal by construction
        A = np.eye(2 * M) - K @ H
        P = A @ Pe
        Pt = A @ Pte @ A.T + K @ Ve @ K.T
        own.append(P)
        true.append(Pt)
    return np.array(own), np.array(true)


def rms_pos_vel(P: np.ndarray, M: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-step RMS over vehicles of the position / velocity sigma: (steps,), (steps,)."""
    d = np.diagonal(P, axis1=1, axis2=2)
    return np.sqrt(d[:, :M].mean(axis=1)), np.sqrt(d[:, M:].mean(axis=1))


def simulate_estimates(cfg: GroupConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Run both estimators on one simulated group; returns errors (steps, 2M) for 'vector' and 'two_stage'."""
    M = cfg.M
    Phi, Q = _dynamics(cfg)
    Cp, V = _measurement(cfg)
    C = observation_matrix(M)
    Ax, Vx = wls(C, _noise(M, cfg.sigma, cfg.sigma_mut))
    Av, Vv = wls(C, _noise(M, cfg.sigma_v, cfg.sigma_vmut))
    x = np.r_[100.0 * np.arange(M), np.full(M, 10.0)]
    P0 = np.diag([cfg.p0_pos**2] * M + [cfg.p0_vel**2] * M)
    xv = x + rng.multivariate_normal(np.zeros(2 * M), P0)
    xs, Pv, Ps = xv.copy(), P0.copy(), P0.copy()
    Hs = np.eye(2 * M) if cfg.use_velocity else np.hstack([np.eye(M), np.zeros((M, M))])
    Rd = np.diag(np.r_[np.diag(Vx), np.diag(Vv)] if cfg.use_velocity else np.diag(Vx))
    err_v, err_s = [], []
    for i in range(cfg.steps):
        if i > 0:
            x = Phi @ x + np.r_[np.zeros(M), cfg.a_x * cfg.T * rng.standard_normal(M)]
            xv, Pv = Phi @ xv, Phi @ Pv @ Phi.T + Q
            xs, Ps = Phi @ xs, Phi @ Ps @ Phi.T + Q
        z = Cp @ x + np.sqrt(np.diag(V)) * rng.standard_normal(len(V))
        K = Pv @ Cp.T @ np.linalg.inv(Cp @ Pv @ Cp.T + V)
        xv, Pv = xv + K @ (z - Cp @ xv), (np.eye(2 * M) - K @ Cp) @ Pv
        zs = Ax @ z[: M * M]
        if cfg.use_velocity:
            zs = np.r_[zs, Av @ z[M * M:]]
        K = Ps @ Hs.T @ np.linalg.inv(Hs @ Ps @ Hs.T + Rd)
        xs, Ps = xs + K @ (zs - Hs @ xs), (np.eye(2 * M) - K @ Hs) @ Ps
        err_v.append(xv - x)
        err_s.append(xs - x)
    return {"vector": np.array(err_v), "two_stage": np.array(err_s)}


def compute_time(cfg: GroupConfig, rng: np.random.Generator, repeats: int = 1) -> dict[str, float]:
    """Wall time (s) of the two estimators, each on its own, for cfg.steps observations (seed fig. 7).

    The two-stage cost is the WLS (done once: C, V constant) + M independent 2x2 filters.
    """
    M = cfg.M
    Phi, Q = _dynamics(cfg)
    Cp, V = _measurement(cfg)
    z = rng.standard_normal((cfg.steps, len(V)))
    t0 = time.perf_counter()
    for _ in range(repeats):
        # information form of seed §3 (P = P_e (E + C^T V^-1 C P_e)^-1): a 2M x 2M solve per step
        CtVi = Cp.T / np.diag(V)[None, :]
        info = CtVi @ Cp
        x, P = np.zeros(2 * M), np.eye(2 * M)
        for zi in z:
            x, P = Phi @ x, Phi @ P @ Phi.T + Q
            P = np.linalg.solve((np.eye(2 * M) + info @ P).T, P.T).T
            x = x + P @ (CtVi @ (zi - Cp @ x))
    t_vec = (time.perf_counter() - t0) / repeats
    C = observation_matrix(M)
    t0 = time.perf_counter()
    for _ in range(repeats):
        Ax, Vx = wls(C, _noise(M, cfg.sigma, cfg.sigma_mut))
        Av, Vv = wls(C, _noise(M, cfg.sigma_v, cfg.sigma_vmut))
        r = np.stack([np.diag(Vx), np.diag(Vv)], 1)  # (M, 2)
        x, P = np.zeros((M, 2)), np.tile(np.eye(2), (M, 1, 1))
        F = np.array([[1.0, cfg.T], [0.0, 1.0]])
        q = np.array([[0.0, 0.0], [0.0, (cfg.a_x * cfg.T) ** 2]])
        for zi in z:
            zs = np.stack([Ax @ zi[: M * M], Av @ zi[M * M:]], 1) if cfg.use_velocity else None
            x, P = x @ F.T, F @ P @ F.T + q
            S = P + r[:, :, None] * np.eye(2)
            K = P @ np.linalg.inv(S)
            x = x + np.einsum("mij,mj->mi", K, zs - x)
            P = P - K @ P
    return {"vector": t_vec, "two_stage": (time.perf_counter() - t0) / repeats}
