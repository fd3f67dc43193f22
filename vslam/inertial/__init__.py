"""Inertial core: the IMU sample gate and buffer, IMU preintegration parameters and windows, static and
visual-inertial initialisation.

GTSAM types (params, pims, biases) stay inside this package and ``vslam.backend``;
the factor graphs themselves are built only in ``vslam.backend``. ``evaluate``
holds the real-data evaluation of preintegration (imported on demand: it reads datasets).
"""

from vslam.inertial.buffer import ImuBuffer
from vslam.inertial.config import InertialConfig
from vslam.inertial.gate import gate_reasons
from vslam.inertial.health import ImuHealth
from vslam.inertial.init import StaticInit, ViAlignment, static_init, vi_align
from vslam.inertial.preintegration import integrate_window, make_bias, make_params, preintegrate, predict, window_segments

__all__ = ["ImuBuffer", "ImuHealth", "InertialConfig", "gate_reasons", "StaticInit", "ViAlignment", "integrate_window", "make_bias", "make_params", "preintegrate",
           "predict", "static_init", "vi_align", "window_segments"]
