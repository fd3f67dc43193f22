"""Map's batched and vectorised bookkeeping equals the plain per-point code it replaces."""

import copy

import numpy as np
import pytest

from vslam.features.base import Features
from vslam.mapping.map import Map, _argmin_median


def _map(n_kf=4, n_kp=60, seed=0) -> Map:
    rng = np.random.default_rng(seed)
    m = Map()
    for k in range(n_kf):
        uv = rng.uniform(0, 300, (n_kp, 2))
        f = Features(uv, uv.copy(), rng.integers(0, 256, (n_kp, 32), dtype=np.uint8), np.zeros(n_kp, np.int64), np.ones(n_kp))
        m.add_keyframe(k, float(k), np.eye(4), f, np.full(n_kp, np.nan), np.full(n_kp, np.nan))
    for i in range(40):  # points seen by 1 to 4 keyframes
        p = m.add_point(rng.normal(size=3), 0, i)
        for k in range(1, int(rng.integers(1, 5))):
            m.add_observation(p.id, k, int(rng.integers(0, n_kp)))
    return m


def _state(m: Map):
    return ([(k, kf.point_ids.tobytes()) for k, kf in m.keyframes.items()],
            [(p.id, p.xyz.tobytes(), p.descriptor.tobytes(), tuple(p.observations.items())) for p in m.points.values()],
            m.revision)


def test_add_free_observations_equals_add_observation():
    m = _map()
    free = np.flatnonzero(m.keyframes[3].point_ids < 0)[:5]
    new = m.add_points(np.ones((5, 3)), 2, np.flatnonzero(m.keyframes[2].point_ids < 0)[:5])
    ref = copy.deepcopy(m)
    m.add_free_observations(new, 3, free)
    for p, kp in zip(new, free):
        ref.add_observation(p, 3, int(kp))
    assert _state(m) == _state(ref)
    with pytest.raises(ValueError):  # keypoints already taken
        m.add_free_observations(new[:2], 3, free[:2])


def test_covisibility_equals_counting_observations():
    m = _map(seed=1)
    for k in m.keyframes:
        counts = {}
        for pid in m.keyframes[k].point_ids[m.keyframes[k].point_ids >= 0]:
            for other in m.points[int(pid)].observations:
                if other != k:
                    counts[other] = counts.get(other, 0) + 1
        got = m.covisibility(k)
        assert got == dict(sorted(counts.items())) and list(got) == sorted(counts)


def test_points_xyz_and_descriptors_equal_stacked_rows():
    m = _map(seed=2)
    ids = np.array(list(m.points)[::-2], np.int64)
    np.testing.assert_array_equal(m.points_xyz(ids), np.array([m.points[int(i)].xyz for i in ids]))
    want = np.array([m.points[int(i)].descriptor for i in ids])
    got = m.descriptors(ids)
    assert got.dtype == want.dtype and got.shape == want.shape and np.array_equal(got, want)
    assert m.points_xyz(ids[:0]).shape == (0, 3) and m.descriptors(ids[:0]).size == 0


@pytest.mark.parametrize("n", [3, 4, 5, 8, 11])
def test_argmin_median_equals_float_median(n):
    """Odd and even counts; small distance ranges make tied medians common (the first row must win)."""
    rng = np.random.default_rng(n)
    for hi in (3, 20, 257):
        dist = rng.integers(0, hi, (50, n, n)).astype(np.int32)
        want = np.argmin(np.median(dist.astype(np.float64), axis=2), axis=1)
        np.testing.assert_array_equal(_argmin_median(dist), want)
