"""Keypoint extractors behind one protocol, and descriptor matching.

``EXTRACTORS`` maps a config name to a factory ``cfg -> Extractor``: "orb" (OpenCV) and "convpoint"
(the learned detector + descriptor, ``features.convpoint``).
"""

from __future__ import annotations

from typing import Callable

from vslam.features.base import Extractor, FeatureConfig, Features
from vslam.features.orb import OrbExtractor


def _convpoint(cfg: FeatureConfig) -> Extractor:
    from vslam.features.convpoint import ConvPointExtractor  # torch is imported only when it is used

    return ConvPointExtractor(cfg)


EXTRACTORS: dict[str, Callable[[FeatureConfig], Extractor]] = {"orb": OrbExtractor, "convpoint": _convpoint}


def make_extractor(cfg: FeatureConfig) -> Extractor:
    from vslam.errors import ConfigError

    if cfg.extractor not in EXTRACTORS:
        raise ConfigError(f"features.extractor: unknown '{cfg.extractor}' (known: {', '.join(sorted(EXTRACTORS))})")
    return EXTRACTORS[cfg.extractor](cfg)


__all__ = ["EXTRACTORS", "Extractor", "FeatureConfig", "Features", "OrbExtractor", "make_extractor"]
