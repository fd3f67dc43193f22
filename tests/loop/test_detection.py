"""Loop candidate detection: covisible / recent keyframes excluded, relative score floor, temporal consistency."""

from __future__ import annotations

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.loop.closing import LoopCloser
from vslam.loop.config import LoopConfig
from vslam.mapping.map import Map

N_KF, DIM = 30, 64


def _map() -> Map:
    """N_KF keyframes in a chain; consecutive keyframes share 20 points (covisible), others none."""
    m = Map()
    for k in range(N_KF):
        z = np.zeros((40, 2))
        f = Features(z, z, np.zeros((40, 32), np.uint8), np.zeros(40, np.int64), np.zeros(40))
        m.add_keyframe(k, float(k), np.eye(4), f, np.full(40, np.nan), np.full(40, np.nan))
    for k in range(N_KF - 1):
        for i in range(20):
            p = m.add_point(np.zeros(3), k, 20 + i)
            m.add_observation(p.id, k + 1, i)
    return m


class _Table:
    """A PlaceDescriptor stand-in: unused here (detect is called with vectors directly)."""

    dim = DIM

    def describe(self, image, features):  # pragma: no cover - not called
        raise AssertionError


def _closer(vecs: np.ndarray, upto: int, cfg: LoopConfig = LoopConfig()) -> LoopCloser:
    cam = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)
    lc = LoopCloser(_map(), cam, StereoCamera(500.0, 500.0, 320.0, 240.0, 0.08), "rgbd", cfg, BackendConfig(),
                    descriptor=_Table())
    for k in range(upto):
        lc.db.add(k, vecs[k])
    return lc


def _vecs() -> np.ndarray:
    """Unit vectors; neighbours in the chain are mildly similar (0.3), keyframe 3/4 resemble 25/26."""
    rng = np.random.default_rng(0)
    base = rng.normal(size=(N_KF, DIM))
    v = base + 0.7 * np.roll(base, 1, axis=0)
    v[25] = base[3] + 0.2 * base[25]
    v[26] = base[4] + 0.2 * base[26]
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def test_consistent_candidates_accepted_on_the_second_keyframe():
    v = _vecs()
    lc = _closer(v, 25, LoopConfig(min_score=0.3))  # above the similarity of unrelated random vectors (~0.2)
    m = lc.map
    assert lc.detect(m.keyframes[25], v[25]) == []  # seen once: not yet consistent
    lc.db.add(25, v[25])
    got = lc.detect(m.keyframes[26], v[26])
    assert got == [4, 5]  # best first; their groups ({3,4,5}, {4,5,6}) overlap those found for keyframe 25


def test_inconsistent_candidates_are_not_accepted():
    v = _vecs()
    v[26] = v[15]  # the next keyframe resembles a different, unconnected place
    lc = _closer(v, 25, LoopConfig(min_score=0.3))
    lc.detect(lc.map.keyframes[25], v[25])
    assert lc.detect(lc.map.keyframes[26], v[26]) == []


def test_covisible_and_recent_keyframes_are_never_candidates():
    v = _vecs()
    lc = _closer(v, 29, LoopConfig(consistency=1, min_kf_gap=10))
    kf = lc.map.keyframes[29]
    q = v[28] + v[22] + 2.0 * v[5]  # resembles its covisible neighbour, a recent keyframe and an old one
    q /= np.linalg.norm(q)
    assert lc.detect(kf, q) == [5]


def test_score_floor_from_the_covisible_neighbours():
    """A candidate less similar than the keyframe's own neighbours is no loop (ORB-SLAM's minScore)."""
    v = _vecs()
    lc = _closer(v, 29, LoopConfig(consistency=1))
    q = v[28] + 0.3 * v[5]
    q /= np.linalg.norm(q)
    assert lc.detect(lc.map.keyframes[29], q) == []
