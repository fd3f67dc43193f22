"""Validity of navigation data by limit values and the priority operating mode (seed 000).

- Limit values (seed 000 §4.2, eqs. 13-14): a measurement error is accepted when it lies in
  the confidence interval (alpha, beta) = (-k sigma, +k sigma), k the two-sided quantile of
  the chosen confidence probability (3-sigma rule: 0.9973). Here the "measurement error" is
  the filter innovation, and sigma its predicted standard deviation.
- Cost of wrong decisions (§4.2, last paragraph): false alarm (a good measurement rejected)
  and missed detection (a gross error accepted) rates, measured against simulated labels.
- Priority mode (seed 000 eqs. 11-12): r_opt = argmin_r J(r) with J(r) = tr P_pos(r), the
  trace of the position covariance of mode r (the seed's J = Tr(P) of §3.2), set to +inf when
  the mode's data fail the limit-value check. The output is x_hat = E(x | z, r_opt) (eq. 12).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


def quantile_factor(confidence: float) -> float:
    """k with P(|N(0,1)| <= k) = confidence; 0.9973 -> 3.0 (eq. 13 with alpha = -beta)."""
    return float(stats.norm.ppf(0.5 * (1.0 + confidence)))


def confidence_interval(mean: np.ndarray, sigma: np.ndarray, confidence: float = 0.9973
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Limit values (alpha, beta) around the expected value (eq. 13)."""
    k = quantile_factor(confidence)
    return mean - k * sigma, mean + k * sigma


def validity_flags(normalized_innov: np.ndarray, k: float = 3.0) -> np.ndarray:
    """True where |innovation| / sigma <= k (valid); NaN (no measurement) -> False."""
    with np.errstate(invalid="ignore"):
        return np.abs(normalized_innov) <= k


@dataclass(frozen=True)
class DecisionRates:
    """Wrong-decision statistics of a limit-value test against ground-truth labels."""

    k: float
    false_alarm: float  # P(rejected | clean)
    missed: float  # P(accepted | gross error)
    cost: float  # c_fa * false_alarm + c_md * missed


def decision_rates(normalized_innov: np.ndarray, is_gross: np.ndarray, k: float,
                   c_fa: float = 1.0, c_md: float = 1.0) -> DecisionRates:
    """Measured false-alarm / missed-detection rates of the |v| <= k sigma test (seed 000 §4.2)."""
    seen = ~np.isnan(normalized_innov)
    valid = validity_flags(normalized_innov, k)
    clean, gross = seen & ~is_gross, seen & is_gross
    fa = float(np.mean(~valid[clean])) if clean.any() else 0.0
    md = float(np.mean(valid[gross])) if gross.any() else 0.0
    return DecisionRates(k, fa, md, c_fa * fa + c_md * md)


@dataclass(frozen=True)
class ModeEstimate:
    """One operating mode's output at common epochs: pos (E, 3) m, cov (E, 3, 3), valid (E,) bool."""

    name: str
    pos: np.ndarray
    cov: np.ndarray
    valid: np.ndarray


def mode_cost(m: ModeEstimate) -> np.ndarray:
    """J(r) per epoch: tr P_pos, +inf where the mode's data are not valid (eq. 11)."""
    J = np.trace(m.cov, axis1=1, axis2=2).astype(float)
    J[~m.valid] = np.inf
    return J


def choose_modes(modes: list[ModeEstimate], hold: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """r_opt = argmin J(r) per epoch (eq. 11) and the fused x_hat = E(x | z, r_opt) (eq. 12).

    hold: minimum number of epochs to stay in a mode (seed: switching dynamics may be
    penalised) unless the current mode becomes invalid. Returns (index (E,), pos (E, 3)).
    """
    J = np.stack([mode_cost(m) for m in modes])  # (R, E)
    idx = np.argmin(J, axis=0)
    if hold > 0:
        cur, since = idx[0], 0
        for e in range(len(idx)):
            since += 1
            if idx[e] != cur and (since >= hold or not np.isfinite(J[cur, e])):
                cur, since = idx[e], 0
            idx[e] = cur
    pos = np.stack([m.pos for m in modes])[idx, np.arange(len(idx))]
    return idx, pos


def interp_track(t_src: np.ndarray, p_src: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation of a (timestamps (T,), positions (T, 3)) track at times t."""
    return np.stack([np.interp(t, t_src, p_src[:, i]) for i in range(3)], axis=1)


def vio_modes(t: np.ndarray, vo_t: np.ndarray, vo_p: np.ndarray, gnss_pos: np.ndarray, gnss_cov: np.ndarray,
              gnss_valid: np.ndarray, drift_per_m: float, noise_m: float
              ) -> tuple[ModeEstimate, ModeEstimate]:
    """The visual modes from a VO/VIO track (timestamps, positions in the navigation axes), e.g. a vslam trajectory.

    VIO: the track anchored at its first epoch e0 (the first navigation epoch inside the track's time span)
    to the GNSS/INS position there, variance (drift * distance since e0)^2 + noise^2.
    VIO+GNSS: the track re-anchored at the last *valid* GNSS/INS epoch (its position and covariance), plus
    the VO drift variance accumulated since that anchor. Both modes are invalid outside the track's span.
    """
    inside = (t >= vo_t[0]) & (t <= vo_t[-1])
    if not inside.any():
        raise ValueError("the VO track does not overlap the navigation epochs")
    e0 = int(np.argmax(inside))
    vo = interp_track(vo_t, vo_p, t)
    vo = vo - vo[e0] + gnss_pos[e0]
    step = np.linalg.norm(np.diff(vo, axis=0), axis=1) * inside[1:]
    dist = np.r_[0.0, np.cumsum(step)]
    var_vio = (drift_per_m * dist) ** 2 + noise_m**2
    vio = ModeEstimate("VIO", vo, var_vio[:, None, None] * np.eye(3), inside.copy())
    pos, cov = np.empty_like(vo), np.empty((len(t), 3, 3))
    a = e0
    for e in range(len(t)):
        if gnss_valid[e] and e >= e0:
            a = e
        pos[e] = gnss_pos[a] + vo[e] - vo[a]
        cov[e] = gnss_cov[a] + ((drift_per_m * (dist[e] - dist[a])) ** 2 + noise_m**2) * np.eye(3)
    return vio, ModeEstimate("VIO+GNSS", pos, cov, inside.copy())
