"""Keypoint extractors behind one protocol, and descriptor matching.

``EXTRACTORS`` maps a config name to a factory ``cfg -> Extractor``: "orb" (OpenCV), "convpoint" (the learned
detector + descriptor trained here, ``features.convpoint``) and "alike-t" / "alike-s" / "alike-n" (the public ALIKE
networks in our architecture, ``features.alike``).
"""

from __future__ import annotations

from typing import Callable

from vslam.features.base import Extractor, FeatureConfig, Features
from vslam.features.orb import OrbExtractor


def _convpoint(cfg: FeatureConfig) -> Extractor:
    from vslam.features.convpoint import ConvPointExtractor  # torch is imported only when it is used

    return ConvPointExtractor(cfg)


def _alike(cfg: FeatureConfig) -> Extractor:
    from vslam.features.alike import AlikeExtractor

    return AlikeExtractor(cfg)


EXTRACTORS: dict[str, Callable[[FeatureConfig], Extractor]] = {"orb": OrbExtractor, "convpoint": _convpoint,
                                                               "alike-t": _alike, "alike-s": _alike, "alike-n": _alike}


def make_extractor(cfg: FeatureConfig) -> Extractor:
    from vslam.errors import ConfigError

    if cfg.extractor not in EXTRACTORS:
        raise ConfigError(f"features.extractor: unknown '{cfg.extractor}' (known: {', '.join(sorted(EXTRACTORS))})")
    return EXTRACTORS[cfg.extractor](cfg)


__all__ = ["EXTRACTORS", "Extractor", "FeatureConfig", "Features", "OrbExtractor", "make_extractor"]
