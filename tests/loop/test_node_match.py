"""Matching within coarse vocabulary nodes (``vslam.loop.node_match``)."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.features.matching import match_mutual
from vslam.loop.node_match import CoarseNodes, match_in_nodes
from vslam.loop.vocabulary import Vocabulary, default_vocabulary_path


@pytest.fixture(scope="module")
def nodes() -> CoarseNodes:
    return CoarseNodes(Vocabulary.load(default_vocabulary_path()), 16)


def _noisy_copies(rng, d: np.ndarray, bits: int) -> np.ndarray:
    """``d`` with ``bits`` random bits flipped per row."""
    out = np.unpackbits(d, axis=1)
    for row in out:
        row[rng.choice(out.shape[1], bits, replace=False)] ^= 1
    return np.packbits(out, axis=1)


def test_one_node_is_exhaustive_matching():
    rng = np.random.default_rng(0)
    d1 = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    d2 = np.concatenate([_noisy_copies(rng, d1[:150], 20), rng.integers(0, 256, (250, 32), dtype=np.uint8)])
    d2[-1] = d2[-2]  # a tie: the lower column wins, as in match_mutual
    for ratio, max_dist in ((0.8, 64), (None, 256), (0.9, 40)):
        want = match_mutual(d1, d2, ratio, max_dist)
        got = match_in_nodes(d1, np.zeros(len(d1), np.int64), d2, np.zeros((len(d2), 1), np.int64), ratio, max_dist)
        np.testing.assert_array_equal(got, want)


def test_pairs_share_a_node_and_probes_find_noisy_copies(nodes):
    rng = np.random.default_rng(1)
    d1 = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    d2 = np.concatenate([_noisy_copies(rng, d1[:200], 30), rng.integers(0, 256, (300, 32), dtype=np.uint8)])
    n1 = nodes.nodes(d1)[:, 0]
    found = {}
    for probes in (1, 2, 3):
        p2 = nodes.nodes(d2, probes)
        assert p2.shape == (len(d2), probes) and all(len(set(r)) == probes for r in p2.tolist())
        m = match_in_nodes(d1, n1, d2, p2, 0.8, 64)
        assert all(n1[i] in p2[j] for i, j in m.tolist())
        true = m[m[:, 1] < 200]
        assert np.all(true[:, 0] == true[:, 1])  # every match of a copy is to its original
        found[probes] = len(true)
    # a copy 30 bits off is often in another node: more probes, more found (random descriptors lie between the
    # nodes, so fewer than for real ones: 90, 127, 147 of the 200 that matching every pair finds)
    assert found[1] < found[2] < found[3]
    assert found[3] >= 0.7 * len(match_mutual(d1, d2, 0.8, 64))


def test_nodes_are_the_same_every_time():
    vocab = Vocabulary.load(default_vocabulary_path())
    d = np.random.default_rng(2).integers(0, 256, (100, 32), dtype=np.uint8)
    np.testing.assert_array_equal(CoarseNodes(vocab, 16).nodes(d, 2), CoarseNodes(vocab, 16).nodes(d, 2))
