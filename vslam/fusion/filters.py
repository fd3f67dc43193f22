"""Gaussian filters for navigation fusion: EKF, cubature KF, square-root CKF and the
adaptive robust square-root CKF of seed 003 (ch. 2, eqs. 1-19).

All filters share one belief type (mean + lower Cholesky factor of the covariance) and
two pure methods, ``predict`` and ``update``, so callers (INS/GNSS, mode choice) can swap
them by name (``FILTERS``). Process / measurement functions are *batched*:
``f(X: (N, n)) -> (N, n)`` and ``h(X: (N, n)) -> (N, m)``, so a cubature filter evaluates
all 2n points in one numpy call.

Seed ambiguities and what we chose (seed 003, ch. 2):
- Eq. 3 writes 2n+1 "sigma points" with delta = phi^2 (n + kappa) - n; with phi = 1,
  kappa = 0 the centre weight vanishes and the rule is the 3rd-degree spherical-radial
  cubature rule (2n points, weights 1/2n). We use that rule (Arasaratnam & Haykin 2009).
- Eq. 9/14 print R~ = R^{T/2} Psi^{-1} R^{-1/2}, which is not a covariance (units of R^0);
  we use the standard MCC form R~ = R^{1/2} Psi^{-1} R^{T/2} (Chen et al. 2017), with
  Psi = diag(G_sigma(xi_i)), G_sigma(e) = exp(-e^2 / 2 sigma^2), xi from eq. 8.
- Eq. 15 scales P_{k|k-1} by alpha_k while eqs. 16-17 reuse the predicted measurement
  points; we regenerate the cubature points from the predicted covariance (standard CKF),
  so scaling the covariance by alpha scales both sums exactly as eqs. 16-17 state.
- Eq. 12 uses the raw innovation v_k (eq. 10) in C_0. An outlier then inflates alpha and
  the filter trusts the *other* channels more for several epochs. ``fading_innovation``
  = "raw" follows the seed; "weighted" (default) feeds C_0 with the MCC-weighted
  innovation Psi^{1/2} v and compares it with R (i.e. the outlier part is removed first).
  Both are measured in the experiments.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from vslam.errors import VslamError

Batched = Callable[[np.ndarray], np.ndarray]


class FilterError(VslamError):
    """A filter got inconsistent shapes or a covariance that is not positive definite."""


@dataclass(frozen=True)
class Belief:
    """Gaussian belief. x: (n,) mean; S: (n, n) lower-triangular with P = S S^T.

    c0 / k carry the innovation-covariance memory of the fading factor (seed 003 eq. 11);
    other filters leave them untouched.
    """

    x: np.ndarray
    S: np.ndarray
    c0: np.ndarray | None = None
    k: int = 0

    @property
    def P(self) -> np.ndarray:
        return self.S @ self.S.T

    @staticmethod
    def from_cov(x: np.ndarray, P: np.ndarray) -> "Belief":
        return Belief(np.asarray(x, float).copy(), safe_cholesky(P))


@dataclass(frozen=True)
class UpdateInfo:
    """What an update saw: innovation v = y - y_hat (m,), its predicted covariance Pyy (m, m),
    MCC weights psi (m,) (ones for non-robust filters) and the fading factor alpha."""

    v: np.ndarray
    Pyy: np.ndarray
    psi: np.ndarray
    alpha: float

    @property
    def nis(self) -> float:
        """Normalised innovation squared, chi^2(m) under the model."""
        return float(self.v @ np.linalg.solve(self.Pyy, self.v))


def safe_cholesky(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a symmetrised P; adds the smallest jitter that works."""
    P = 0.5 * (P + P.T)
    jitter = 0.0
    scale = max(float(np.max(np.abs(np.diag(P)))), 1e-300)
    for _ in range(8):
        try:
            return np.linalg.cholesky(P + jitter * np.eye(len(P)))
        except np.linalg.LinAlgError:
            jitter = scale * 1e-12 if jitter == 0.0 else jitter * 100.0
    raise FilterError("covariance is not positive definite (even with jitter)")


def tria(A: np.ndarray) -> np.ndarray:
    """Lower-triangular S with S S^T = A A^T, by QR of A^T (square-root filters)."""
    r = np.linalg.qr(A.T, mode="r")
    S = r.T
    n = A.shape[0]
    S = S[:n, :n]
    signs = np.sign(np.diag(S))
    signs[signs == 0] = 1.0
    return S * signs


def cubature_points(x: np.ndarray, S: np.ndarray) -> np.ndarray:
    """2n points x +- sqrt(n) S e_i (seed 003 eq. 3 with delta = 0). Returns (2n, n)."""
    n = len(x)
    D = np.sqrt(n) * S.T  # rows are the scaled columns of S
    return np.vstack([x + D, x - D])


def numerical_jacobian(fun: Batched, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central differences of a batched function at x; (m, n)."""
    n = len(x)
    step = eps * np.maximum(1.0, np.abs(x))
    X = np.vstack([x + np.diag(step), x - np.diag(step)])
    Y = fun(X)
    return ((Y[:n] - Y[n:]) / (2 * step[:, None])).T


@dataclass(frozen=True)
class ExtendedKF:
    """Extended Kalman filter (seed 000 eq. 10 with Jacobians); Joseph-form covariance update."""

    name: str = "ekf"

    def predict(self, b: Belief, f: Batched, Q: np.ndarray, F: np.ndarray | None = None) -> Belief:
        F = numerical_jacobian(f, b.x) if F is None else F
        x = f(b.x[None, :])[0]
        return dataclasses.replace(b, x=x, S=safe_cholesky(F @ b.P @ F.T + Q))

    def update(self, b: Belief, y: np.ndarray, h: Batched, R: np.ndarray,
               H: np.ndarray | None = None) -> tuple[Belief, UpdateInfo]:
        H = numerical_jacobian(h, b.x) if H is None else H
        P = b.P
        v = y - h(b.x[None, :])[0]
        Pyy = H @ P @ H.T + R
        K = np.linalg.solve(Pyy, H @ P).T
        A = np.eye(len(b.x)) - K @ H
        Pn = A @ P @ A.T + K @ R @ K.T
        info = UpdateInfo(v, Pyy, np.ones(len(y)), 1.0)
        return dataclasses.replace(b, x=b.x + K @ v, S=safe_cholesky(Pn)), info


@dataclass(frozen=True)
class CubatureKF:
    """Cubature Kalman filter in covariance form (seed 003 eqs. 3-7, 16-19 with alpha = 1, R~ = R)."""

    name: str = "ckf"

    def predict(self, b: Belief, f: Batched, Q: np.ndarray, F: np.ndarray | None = None) -> Belief:
        Xp = f(cubature_points(b.x, b.S))
        x = Xp.mean(axis=0)
        d = Xp - x
        P = d.T @ d / len(Xp) + Q  # eq. 5
        return dataclasses.replace(b, x=x, S=safe_cholesky(P))

    def update(self, b: Belief, y: np.ndarray, h: Batched, R: np.ndarray,
               H: np.ndarray | None = None) -> tuple[Belief, UpdateInfo]:
        X = cubature_points(b.x, b.S)
        Y = h(X)  # eq. 6
        yh = Y.mean(axis=0)  # eq. 7
        dX, dY = (X - b.x) / np.sqrt(len(X)), (Y - yh) / np.sqrt(len(X))
        Pyy = dY.T @ dY + R  # eq. 16
        Pxy = dX.T @ dY  # eq. 17
        K = np.linalg.solve(Pyy, Pxy.T).T
        v = y - yh
        P = b.P - K @ Pyy @ K.T  # eq. 18
        info = UpdateInfo(v, Pyy, np.ones(len(y)), 1.0)
        return dataclasses.replace(b, x=b.x + K @ v, S=safe_cholesky(P)), info


def _sr_predict(b: Belief, f: Batched, Q: np.ndarray) -> Belief:
    """SR-CKF time update: S^- = tria([X* centred / sqrt(2n), sqrt(Q)]) (eqs. 4-5 in square-root form)."""
    Xp = f(cubature_points(b.x, b.S))
    x = Xp.mean(axis=0)
    dX = (Xp - x).T / np.sqrt(len(Xp))
    return dataclasses.replace(b, x=x, S=tria(np.hstack([dX, safe_cholesky(Q)])))


def _sr_gain_update(b: Belief, dX: np.ndarray, dY: np.ndarray, SR: np.ndarray,
                    v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shared square-root measurement update; dX (n, 2n), dY (m, 2n) are centred, scaled points.

    Returns (x_post, S_post, Pyy). Pyy = Syy Syy^T with Syy = tria([dY, SR]) (eq. 16),
    K = Pxy Syy^-T Syy^-1 (eqs. 17-19), S+ = tria([dX - K dY, K SR]) (eq. 18 as a QR).
    """
    Syy = tria(np.hstack([dY, SR]))
    Pxy = dX @ dY.T
    # np.linalg.solve, not scipy's solve_triangular: the latter's per-call cost on small matrices here
    # (threaded OpenBLAS) dominates a Monte-Carlo run (docs/fusion.md).
    K = np.linalg.solve(Syy.T, np.linalg.solve(Syy, Pxy.T)).T
    S = tria(np.hstack([dX - K @ dY, K @ SR]))
    return b.x + K @ v, S, Syy @ Syy.T


@dataclass(frozen=True)
class SquareRootCKF:
    """Square-root cubature KF: propagates S by QR only, so P stays symmetric positive definite."""

    name: str = "srckf"

    def predict(self, b: Belief, f: Batched, Q: np.ndarray, F: np.ndarray | None = None) -> Belief:
        return _sr_predict(b, f, Q)

    def update(self, b: Belief, y: np.ndarray, h: Batched, R: np.ndarray,
               H: np.ndarray | None = None) -> tuple[Belief, UpdateInfo]:
        X = cubature_points(b.x, b.S)
        Y = h(X)
        yh = Y.mean(axis=0)
        dX, dY = (X - b.x).T / np.sqrt(len(X)), (Y - yh).T / np.sqrt(len(X))
        v = y - yh
        x, S, Pyy = _sr_gain_update(b, dX, dY, safe_cholesky(R), v)
        return dataclasses.replace(b, x=x, S=S), UpdateInfo(v, Pyy, np.ones(len(y)), 1.0)


@dataclass(frozen=True)
class AdaptiveRobustConfig:
    """Knobs of the seed-003 filter.

    kernel_sigma: width of the Gaussian correntropy kernel on the R-whitened innovation
        (eq. 8); inf disables MCC (Psi = I). Smaller = more aggressive outlier rejection.
    min_weight: floor on Psi_ii so R~ stays finite (an outlier gets R / min_weight).
    fading: apply the fading factor alpha_k (eqs. 10-13); False gives alpha = 1.
    forgetting: lambda of eq. 11 (weight of the old C_0; new term weight 1/(1+lambda)).
    fading_innovation: "raw" = eq. 11 as printed; "weighted" = MCC-weighted innovation.
    whiten_fading: take the traces of eq. 12 after whitening by R^{-1/2}, so metres and m/s
        channels count equally (the printed traces mix units; pseudoranges dominate).
    kernel_normalization: "R" = xi = R^{-1/2} v (eq. 8); "innovation" = xi = Pyy^{-1/2} v, which
        does not mistake a large *state* uncertainty for an outlier (after an outage).
    """

    kernel_sigma: float = 3.0
    min_weight: float = 1e-6
    fading: bool = True
    forgetting: float = 0.95
    fading_innovation: Literal["raw", "weighted"] = "weighted"
    whiten_fading: bool = True
    kernel_normalization: Literal["R", "innovation"] = "R"


@dataclass(frozen=True)
class AdaptiveRobustSRCKF:
    """Adaptive robust square-root CKF with maximum-correntropy update (seed 003 ch. 2, eqs. 1-19)."""

    cfg: AdaptiveRobustConfig = field(default_factory=AdaptiveRobustConfig)
    name: str = "arsckf"

    def predict(self, b: Belief, f: Batched, Q: np.ndarray, F: np.ndarray | None = None) -> Belief:
        return _sr_predict(b, f, Q)

    def mcc_weights(self, v: np.ndarray, SR: np.ndarray, dY: np.ndarray) -> np.ndarray:
        """Psi_ii = G_sigma(xi_i), xi = R^{-1/2} v (eqs. 8-9) or Pyy^{-1/2} v (see config)."""
        if not np.isfinite(self.cfg.kernel_sigma):
            return np.ones(len(v))
        if self.cfg.kernel_normalization == "innovation":
            xi = np.linalg.solve(tria(np.hstack([dY, SR])), v)
        else:
            xi = np.linalg.solve(SR, v)
        return np.maximum(np.exp(-0.5 * (xi / self.cfg.kernel_sigma) ** 2), self.cfg.min_weight)

    def fading_factor(self, b: Belief, v_c0: np.ndarray, SR: np.ndarray,
                      dY: np.ndarray) -> tuple[float, np.ndarray, int]:
        """alpha_k from eqs. 10-13; returns (alpha, C0, k). C0 restarts when m changes."""
        R = SR @ SR.T
        if self.cfg.whiten_fading:
            v_c0, dY, R = np.linalg.solve(SR, v_c0), np.linalg.solve(SR, dY), np.eye(len(v_c0))
        vv = np.outer(v_c0, v_c0)
        same = b.c0 is not None and b.c0.shape == vv.shape
        lam = self.cfg.forgetting
        c0 = (lam * b.c0 + vv) / (1.0 + lam) if same else vv  # eq. 11
        k = b.k + 1 if same else 1
        if not self.cfg.fading:
            return 1.0, c0, k
        denom = float(np.sum(dY * dY))  # tr(sum w (y_i - y)(y_i - y)^T)
        alpha0 = float(np.trace(c0 - R)) / denom if denom > 0 else 1.0  # eq. 12
        return (alpha0 if alpha0 > 1.0 else 1.0), c0, k  # eq. 13

    def update(self, b: Belief, y: np.ndarray, h: Batched, R: np.ndarray,
               H: np.ndarray | None = None) -> tuple[Belief, UpdateInfo]:
        X = cubature_points(b.x, b.S)
        Y = h(X)  # eq. 6
        yh = Y.mean(axis=0)  # eq. 7
        dX, dY = (X - b.x).T / np.sqrt(len(X)), (Y - yh).T / np.sqrt(len(X))
        v = y - yh  # eq. 10
        SR = safe_cholesky(R)
        psi = self.mcc_weights(v, SR, dY)  # eqs. 8-9
        v_c0 = v if self.cfg.fading_innovation == "raw" else np.sqrt(psi) * v
        alpha, c0, k = self.fading_factor(b, v_c0, SR, dY)  # eqs. 11-13
        SRt = SR / np.sqrt(psi)[None, :]  # R~^{1/2} = R^{1/2} Psi^{-1/2} (eq. 14)
        sa = np.sqrt(alpha)  # eqs. 15-17: alpha scales P^-, hence both centred point sets
        x, S, _ = _sr_gain_update(b, sa * dX, sa * dY, SRt, v)  # eqs. 16-19
        # report Pyy with the nominal R: validity tests must not see the outlier-inflated R~
        Pyy = alpha * dY @ dY.T + R
        return Belief(x, S, c0, k), UpdateInfo(v, Pyy, psi, alpha)


def kalman_exact(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray, H: np.ndarray,
                 R: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference linear KF (predict then update for each row of ys). Returns means (T, n), covs (T, n, n)."""
    xs, Ps = [], []
    for y in ys:
        x, P = F @ x, F @ P @ F.T + Q
        Syy = H @ P @ H.T + R
        K = np.linalg.solve(Syy, H @ P).T
        x, P = x + K @ (y - H @ x), P - K @ Syy @ K.T
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def make_filter(name: str, robust: AdaptiveRobustConfig | None = None):
    """Filter by name: 'ekf', 'ckf', 'srckf', 'arsckf' (seed 003), 'mcc-srckf' (arsckf without fading)."""
    if name == "arsckf":
        return AdaptiveRobustSRCKF(robust or AdaptiveRobustConfig())
    if name == "mcc-srckf":
        return AdaptiveRobustSRCKF(dataclasses.replace(robust or AdaptiveRobustConfig(), fading=False), name=name)
    if name not in FILTERS:
        raise FilterError(f"unknown filter {name!r} (known: {', '.join(FILTERS)})")
    return FILTERS[name]()


FILTERS = {"ekf": ExtendedKF, "ckf": CubatureKF, "srckf": SquareRootCKF, "arsckf": AdaptiveRobustSRCKF,
           "mcc-srckf": AdaptiveRobustSRCKF}
