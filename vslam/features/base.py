"""The keypoint-extractor plug-in interface: ``Features`` and the ``Extractor`` protocol.

Every extractor (ORB today, the learned ConvPoint later) returns the same
``Features`` so that matching, tracking and mapping never look at which one
produced them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from vslam.data.types import PinholeCamera
from vslam.errors import ConfigError


@dataclass(frozen=True)
class FeatureConfig:
    """Front-end settings. ``grid_*``: bucketing cells so texture-rich corners do not take every keypoint."""

    extractor: str = "orb"  # key of EXTRACTORS
    n_features: int = 1500
    scale_factor: float = 1.2  # image pyramid step between octaves
    n_levels: int = 8
    fast_threshold: int = 12  # FAST corner threshold (OpenCV's default 20 starves low-contrast images)
    # Poor light: when fewer than fast_retry_below x n_features corners pass fast_threshold on a low-contrast
    # image (5th to 95th intensity percentile less than low_contrast_spread grey levels apart), detection runs
    # again at fast_threshold_min and bucketing (strongest first in each cell) fills the cells that had none
    # (ORB-SLAM's iniThFAST / minThFAST, per image instead of per cell): it keeps tracking alive on a dim
    # corridor. Not on every image short of corners: on a plain one it doubles the keyframes and halves the
    # frame rate, and a blurred image (few corners at full contrast) gets displaced ones. Bright images spread
    # well above low_contrast_spread (docs/features.md, 'Measurements behind settings in the code').
    # fast_threshold_min >= fast_threshold: off.
    fast_threshold_min: int = 5
    fast_retry_below: float = 0.5
    low_contrast_spread: float = 50.0
    oversample: float = 3.0  # detect this many times n_features, then bucket
    grid_cols: int = 16
    grid_rows: int = 12
    # extractor "convpoint" (the learned detector + descriptor)
    weights: str = ""  # "" = the shipped vslam/models/convpoint_v1.pt
    device: str = "auto"  # auto = CUDA when available
    conf_thresh: float = 0.005  # keypoint probability after NMS
    nms_radius: int = 4  # pixels
    bf16: bool = False  # network in bfloat16 autocast: faster on CPUs with AVX512-BF16, not bit-identical
    # On the CPU, the network in int8 (``vslam.quantize``; ranges in <weights>.int8.json, made by `vslam quantize
    # keypoints`; without them, or on CUDA, the float network runs): faster convolutions, keypoints and
    # descriptors a little off the float ones (docs/features.md, 'Measurements behind settings in the code').
    int8: bool = True
    # extractors alike-t / alike-s / alike-n: the network sees the image resized by this; None: the extractor's
    # own default (``features.alike.DEFAULT_INPUT_SCALE``, half resolution: a quarter of the cost; two-view pose
    # accuracy and speed per setting in docs/features.md). ``weights`` "" = the shipped vslam/models/alike_<variant>.pt.
    input_scale: float | None = None
    min_score: float = 0.2  # alike-*: score floor of a keypoint (the published code's threshold)
    # alike-*: what runs the network's dense part, "torch" or "onnxruntime" (the same maps to float rounding; faster
    # on two threads of a loaded machine, the same on one: docs/features.md)
    runtime: str = "torch"

    def __post_init__(self) -> None:
        if self.n_features < 1:
            raise ConfigError(f"slam.features.n_features must be at least 1, got {self.n_features}")
        if self.n_levels < 1 or not self.scale_factor > 1.0:
            raise ConfigError(f"slam.features: n_levels must be >= 1 and scale_factor > 1, got {self.n_levels}, "
                              f"{self.scale_factor}")
        if self.input_scale is not None and not 0.0 < self.input_scale <= 1.0:
            raise ConfigError(f"slam.features.input_scale must be in (0, 1], got {self.input_scale}")
        if self.runtime not in ("torch", "onnxruntime"):
            raise ConfigError(f"slam.features.runtime must be torch or onnxruntime, got {self.runtime!r}")


@dataclass
class Features:
    """Keypoints of one image.

    raw: (N,2) float64 pixels as detected (distorted image).
    uv: (N,2) float64 ideal (undistorted) pixels of the same K.
    desc: (N,D) descriptors (uint8 bits for binary, float32 for learned).
    octave: (N,) int pyramid level; response: (N,) float detector score.
    scale_factor: pyramid step, so level l has scale ``scale_factor**l``.
    """

    raw: np.ndarray
    uv: np.ndarray
    desc: np.ndarray
    octave: np.ndarray
    response: np.ndarray
    scale_factor: float = 1.2

    def __len__(self) -> int:
        return len(self.uv)

    @staticmethod
    def empty(dim: int = 32, dtype: type = np.uint8, scale_factor: float = 1.2) -> Features:
        z2 = np.zeros((0, 2))
        return Features(z2, z2.copy(), np.zeros((0, dim), dtype), np.zeros(0, np.int64), np.zeros(0), scale_factor)

    def level_scale(self) -> np.ndarray:
        """(N,) pixel scale of each keypoint's octave (1 at full resolution)."""
        return self.scale_factor ** self.octave.astype(np.float64)

    def subset(self, idx: np.ndarray) -> Features:
        return Features(self.raw[idx], self.uv[idx], self.desc[idx], self.octave[idx], self.response[idx], self.scale_factor)


class Extractor(Protocol):
    """detect(image, camera) -> Features. ``descriptor_kind`` tells matching which distance to use."""

    descriptor_kind: Literal["binary", "float"]

    def detect(self, image: np.ndarray, camera: PinholeCamera, mask: np.ndarray | None = None) -> Features: ...
