"""Global place descriptors: one L2-normalised vector per image, compared by dot product.

``PlaceDescriptor`` is the plug-in interface the keyframe database, loop
detection and relocalisation use; the learned one is ``VladNetDescriptor``
(``vslam.loop.vladnet``, weights vslam/models/vladnet_v1.pt). ``BowDescriptor`` is the non-learned
baseline: a tf-idf bag of ORB words (DBoW2's weighting) over the keypoints the
tracker already extracted, so it costs one word assignment per keyframe.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from vslam.errors import ConfigError
from vslam.features.base import Features
from vslam.loop.vocabulary import Vocabulary, default_vocabulary_path
from vslam.resources import shipped_model


class PlaceDescriptor(Protocol):
    """describe(image, features) -> (D,) float32 with unit L2 norm (all zeros when nothing to describe).

    image: (H,W[,3]) uint8; features: the tracker's keypoints of that image (a descriptor may ignore
    either input). ``dim``: D.
    """

    dim: int

    def describe(self, image: np.ndarray | None, features: Features | None) -> np.ndarray: ...


class BowDescriptor:
    """tf-idf bag of binary words: v_w = (n_w / N) * idf_w, then L2 normalised (cosine = dot)."""

    def __init__(self, vocabulary: Vocabulary):
        self.vocab = vocabulary
        self.dim = vocabulary.size

    def words(self, features: Features) -> np.ndarray:
        """(N,) word index of each keypoint (binary descriptors only)."""
        if features.desc.dtype != np.uint8:
            raise TypeError("BowDescriptor needs binary (uint8) descriptors, e.g. ORB")
        return self.vocab.assign(features.desc)

    def describe(self, image: np.ndarray | None, features: Features | None) -> np.ndarray:
        v = np.zeros(self.dim, np.float32)
        if features is None or len(features) == 0:
            return v
        w = self.words(features)
        np.add.at(v, w, 1.0)
        v *= self.vocab.idf / len(w)
        n = float(np.linalg.norm(v))
        return v / n if n > 0 else v


def default_vladnet_path() -> Path:
    return shipped_model("vladnet_v1.pt")


def make_place_descriptor(kind: str, vocabulary: str = "", weights: str = "") -> PlaceDescriptor:
    """Registry by name: ``bow`` (vocabulary file; "" = the shipped vslam/models/orb_bow_k512.npz) or ``vladnet``
    (weights file; "" = the shipped vslam/models/vladnet_v1.pt; torch is imported only then)."""
    if kind == "bow":
        return BowDescriptor(Vocabulary.load(Path(vocabulary) if vocabulary else default_vocabulary_path()))
    if kind == "vladnet":
        from vslam.loop.vladnet import VladNetDescriptor

        return VladNetDescriptor.from_file(Path(weights) if weights else default_vladnet_path())
    raise ConfigError(f"slam.loop.descriptor: unknown place descriptor {kind!r} (known: bow, vladnet)")
