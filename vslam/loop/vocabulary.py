"""A flat visual vocabulary of binary ORB words, trained by k-majority (binary k-means).

Bag-of-words place recognition (Gálvez-López & Tardós, DBoW2) quantises each
256-bit ORB descriptor to its nearest *word*; an image becomes a tf-idf
weighted word histogram. We keep one flat level of ``K`` words (K ~ 500-1000):
assignment is one float matrix product on +-1 bit vectors, fast enough in
numpy for 1500 keypoints per keyframe, and the vocabulary is an 8-32 KB file.

Training: k-means on the unpacked bits with the majority vote as the centre
(k-majority), k-means++ seeding from a passed ``np.random.Generator`` so the
file is reproducible. ``python -m vslam.loop.vocabulary`` trains the shipped
``vslam/models/orb_bow_k512.npz`` from COCO images (generic photos, none from the
sequences we evaluate on).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vslam.errors import ConfigError
from vslam.resources import shipped_model

log = logging.getLogger(__name__)

VOCAB_VERSION = 1


def unpack_pm1(desc: np.ndarray) -> np.ndarray:
    """(N,32) uint8 binary descriptors -> (N,256) float32 in {-1,+1}; Hamming = (256 - a.b) / 2."""
    bits = np.unpackbits(np.ascontiguousarray(desc, dtype=np.uint8), axis=1).astype(np.float32)
    return 2.0 * bits - 1.0


@dataclass
class Vocabulary:
    """words: (K,32) uint8 binary centres; idf: (K,) float32 log(N_images / images containing the word)."""

    words: np.ndarray
    idf: np.ndarray

    def __post_init__(self) -> None:
        self._pm1 = unpack_pm1(self.words)  # (K,256) cached for assignment

    @property
    def size(self) -> int:
        return len(self.words)

    def assign(self, desc: np.ndarray) -> np.ndarray:
        """(N,32) uint8 -> (N,) int64 index of the nearest word (Hamming; ties: lowest index)."""
        if len(desc) == 0:
            return np.zeros(0, np.int64)
        dots = unpack_pm1(desc) @ self._pm1.T  # largest dot = smallest Hamming distance
        return np.argmax(dots, axis=1).astype(np.int64)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, words=self.words, idf=self.idf, version=np.int64(VOCAB_VERSION))
        return path

    @staticmethod
    def load(path: str | Path) -> Vocabulary:
        if not Path(path).is_file():
            raise ConfigError(f"{path}: vocabulary file not found (slam.loop.vocabulary)")
        try:
            with np.load(Path(path), allow_pickle=False) as z:
                version = int(z["version"])
                words, idf = z["words"].astype(np.uint8), z["idf"].astype(np.float32)
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"{path}: not a vocabulary file ({e})") from None
        if version != VOCAB_VERSION:
            raise ConfigError(f"{path}: vocabulary version {version}, expected {VOCAB_VERSION}")
        return Vocabulary(words, idf)


def _kmeanspp(X: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding on +-1 vectors (squared Hamming as the D^2 weight). -> (k,256) centres."""
    centres = [X[int(rng.integers(len(X)))]]
    d = (256.0 - X @ centres[0]) / 2.0
    for _ in range(1, k):
        p = d * d
        i = int(rng.choice(len(X), p=p / p.sum())) if p.sum() > 0 else int(rng.integers(len(X)))
        centres.append(X[i])
        d = np.minimum(d, (256.0 - X @ X[i]) / 2.0)
    return np.stack(centres)


def train_vocabulary(descs_per_image: list[np.ndarray], k: int, rng: np.random.Generator, iterations: int = 15,
                     max_train: int = 100_000) -> Vocabulary:
    """k-majority over ORB descriptors of many images; idf from the same images.

    descs_per_image: list of (N_i,32) uint8; at most ``max_train`` descriptors (random subset) train the words.
    """
    all_desc = np.concatenate([d for d in descs_per_image if len(d)])
    sub = all_desc if len(all_desc) <= max_train else all_desc[np.sort(rng.choice(len(all_desc), max_train, replace=False))]
    X = unpack_pm1(sub)
    C = _kmeanspp(X, k, rng)
    for it in range(iterations):
        a = np.argmax(X @ C.T, axis=1)
        newC = C.copy()
        for j in range(k):
            m = a == j
            if m.any():
                s = X[m].sum(axis=0)
                newC[j] = np.where(s >= 0, 1.0, -1.0)  # majority vote per bit (ties -> 1)
        moved = int(np.count_nonzero(np.any(newC != C, axis=1)))
        C = newC
        log.info("k-majority iteration %d: %d words moved", it, moved)
        if moved == 0:
            break
    words = np.packbits((C > 0).astype(np.uint8), axis=1)
    vocab = Vocabulary(words, np.ones(k, np.float32))
    df = np.zeros(k, np.float64)
    for d in descs_per_image:
        if len(d):
            df[np.unique(vocab.assign(d))] += 1
    vocab.idf = np.log(len(descs_per_image) / np.maximum(df, 1.0)).astype(np.float32)
    return vocab


def default_vocabulary_path() -> Path:
    return shipped_model("orb_bow_k512.npz")


def main(argv: list[str] | None = None) -> None:
    """Train the shipped vocabulary: ORB (the tracker's settings) on every image of a folder tree."""
    import cv2

    from vslam.features import FeatureConfig
    from vslam.features.orb import orb_detector

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("images", type=Path, help="folder searched recursively for .jpg/.png")
    p.add_argument("-o", "--output", type=Path, default=default_vocabulary_path())
    p.add_argument("-k", type=int, default=512)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    fc = FeatureConfig()
    orb = orb_detector(fc, fc.n_features, fc.fast_threshold)
    files = sorted(f for f in a.images.rglob("*") if f.suffix.lower() in (".jpg", ".png"))
    descs = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            continue
        _, d = orb.detectAndCompute(img, None)
        if d is not None:
            descs.append(d)
    log.info("%d images, %d descriptors", len(descs), sum(len(d) for d in descs))
    vocab = train_vocabulary(descs, a.k, np.random.default_rng(a.seed))
    log.info("wrote %s", vocab.save(a.output))


if __name__ == "__main__":
    main()
