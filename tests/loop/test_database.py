"""Keyframe database and the bag-of-words place descriptor."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.features.base import Features
from vslam.loop.database import KeyframeDatabase
from vslam.loop.descriptor import BowDescriptor, make_place_descriptor
from vslam.loop.vocabulary import Vocabulary, train_vocabulary, unpack_pm1


def _unit(rng, n, d):
    v = rng.normal(size=(n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_query_top_k_exclude_and_remove():
    rng = np.random.default_rng(0)
    V = _unit(rng, 40, 32)
    db = KeyframeDatabase(32)
    for i, v in enumerate(V):
        db.add(100 + i, v)
    q = V[7] + 0.05 * V[3]
    res = db.query(q / np.linalg.norm(q), 3)
    assert res[0][0] == 107 and res[0][1] > 0.99
    assert [r[0] for r in db.query(V[7], 3, exclude={107})][0] != 107
    assert db.query(V[7], 5, min_score=0.999) == [(107, pytest.approx(1.0, abs=1e-5))]
    db.remove(107)
    assert 107 not in db and len(db) == 39
    assert all(k != 107 for k, _ in db.query(V[7], 39))
    np.testing.assert_allclose(db.vector(139), V[39])  # the moved last row is still found by id
    assert db.memory_bytes() == 39 * 32 * 4


def test_vocabulary_training_is_deterministic_and_assigns_nearest_word():
    rng = np.random.default_rng(0)
    centres = rng.integers(0, 256, (8, 32), dtype=np.uint8)
    images = []
    for i in range(16):  # each "image" holds noisy copies of two centres (a few flipped bits)
        idx = rng.integers(0, 8, 60)
        d = centres[idx].copy()
        flip = rng.integers(0, 256, d.shape, dtype=np.uint8) & rng.integers(0, 256, d.shape, dtype=np.uint8) & 0x11
        images.append(d ^ flip)
    a = train_vocabulary(images, 8, np.random.default_rng(1))
    b = train_vocabulary(images, 8, np.random.default_rng(1))
    np.testing.assert_array_equal(a.words, b.words)
    # every true centre is (almost) a word, and assignment is the exact Hamming nearest
    ham = ((256 - unpack_pm1(centres) @ unpack_pm1(a.words).T) / 2).min(axis=1)
    assert ham.max() <= 8
    q = images[0]
    brute = ((256 - unpack_pm1(q) @ unpack_pm1(a.words).T) / 2).argmin(axis=1)
    np.testing.assert_array_equal(a.assign(q), brute)


def test_bow_descriptor_unit_norm_and_similarity(tmp_path):
    rng = np.random.default_rng(2)
    words = rng.integers(0, 256, (64, 32), dtype=np.uint8)
    vocab = Vocabulary(words, np.ones(64, np.float32))
    path = vocab.save(tmp_path / "v.npz")
    desc = make_place_descriptor("bow", str(path))
    assert isinstance(desc, BowDescriptor) and desc.dim == 64

    def feats(d):
        z = np.zeros((len(d), 2))
        return Features(z, z, d, np.zeros(len(d), np.int64), np.zeros(len(d)))

    a = feats(words[rng.integers(0, 32, 300)])  # uses words 0..31
    b = feats(words[rng.integers(0, 32, 300)])
    c = feats(words[32 + rng.integers(0, 32, 300)])  # a different place: words 32..63
    va, vb, vc = (desc.describe(None, f) for f in (a, b, c))
    assert np.linalg.norm(va) == pytest.approx(1.0, abs=1e-6)
    assert va @ vb > 0.9 and abs(va @ vc) < 1e-6
    assert not desc.describe(None, feats(words[:0])).any()


def test_shipped_vocabulary_loads():
    v = make_place_descriptor("bow")
    assert v.dim == 512
