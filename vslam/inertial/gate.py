"""The IMU sample gate: a reading is believed only if the sensor could have produced it and it agrees with its
neighbours.

Two tests, per sample and axis (a sample fails when any axis of either sensor fails):

* range -- a reading at or beyond the sensor's full scale (``InertialConfig.accel_range`` / ``gyro_range``) is
  clipped or corrupt: the true value is unknown either way;
* spike -- a Hampel test: ``|x - median| > max(spike_sigmas * 1.4826 * MAD, floor)`` over the
  ``2 spike_window + 1`` samples around it (fewer at the ends of the data). The median follows real motion
  (a smooth signal sits on its local median), the MAD scale widens the test where the signal is rough (rotor
  vibration), and the absolute floor (``spike_floor_accel`` / ``spike_floor_gyro``) keeps a quiet stretch from
  turning ordinary vibration into outliers. Up to ``spike_window`` consecutive bad samples are caught (the
  median's breakdown point); a longer corrupt stretch is not a spike and is left to the IMU factor's
  consistency test in the visual-inertial BA (``vslam.backend.inertial``).

Rejected samples are dropped, not replaced: preintegration integrates the linear interpolation of the samples
it is given, whatever their spacing, and a hole longer than ``max_gap_s`` turns the inertial factors off
(``vslam.tracking.vio``). Readings that were out of range do not enter the spike test's medians.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

if TYPE_CHECKING:
    from vslam.inertial.config import InertialConfig

OK, RANGE, SPIKE = 0, 1, 2
REASONS = ("ok", "range", "spike")
MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution from its median absolute deviation


def range_outliers(x: np.ndarray, full_scale: float) -> np.ndarray:
    """(N,) bool: some axis of x (N,3) at or beyond +-full_scale (or not finite)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        return ~np.all(np.abs(x) < full_scale, axis=1)


def hampel_outliers(x: np.ndarray, k: int, n_sigmas: float, floor: float) -> np.ndarray:
    """(N,) bool: samples of x (N,3) whose some axis departs from the median of its 2k+1 neighbourhood
    (truncated at the ends; NaN entries are ignored) by more than max(n_sigmas * 1.4826 * MAD, floor)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    if len(x) < 3:
        return np.zeros(len(x), dtype=bool)
    pad = np.pad(x, ((k, k), (0, 0)), constant_values=np.nan)
    win = sliding_window_view(pad, 2 * k + 1, axis=0)  # (N, 3, 2k+1)
    with np.errstate(invalid="ignore"):
        med = _nanmedian_last(win)
        scale = MAD_TO_SIGMA * _nanmedian_last(np.abs(win - med[..., None]))
        return np.any(np.abs(x - med) > np.maximum(n_sigmas * scale, floor), axis=1)


def _nanmedian_last(w: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN (NaN where all are): ``np.nanmedian`` without its per-call cost,
    which dominated the gate on the few samples a frame brings."""
    s = np.sort(w, axis=-1)  # NaN last; all NaN: both picks are NaN
    n = np.sum(~np.isnan(w), axis=-1, keepdims=True)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0), axis=-1)
    hi = np.take_along_axis(s, n // 2, axis=-1)
    return 0.5 * (lo + hi)[..., 0]


def gate_reasons(gyro: np.ndarray, accel: np.ndarray, cfg: InertialConfig) -> np.ndarray:
    """(N,) int8 per sample: OK, RANGE or SPIKE (``REASONS`` names them); gyro rad/s, accel m/s^2, (N,3) each."""
    gyro = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    accel = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(gyro), dtype=np.int8)
    bad = range_outliers(gyro, cfg.gyro_range) | range_outliers(accel, cfg.accel_range)
    out[bad] = RANGE
    g, a = gyro.copy(), accel.copy()
    g[bad], a[bad] = np.nan, np.nan
    spike = (hampel_outliers(g, cfg.spike_window, cfg.spike_sigmas, cfg.spike_floor_gyro)
             | hampel_outliers(a, cfg.spike_window, cfg.spike_sigmas, cfg.spike_floor_accel))
    out[spike & ~bad] = SPIKE
    return out
