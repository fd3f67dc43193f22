"""Local BA's plumbing: the factor cache, vectorised keys and factor building, the window's point arrays give
exactly what the plain per-observation code gives."""

from __future__ import annotations

import dataclasses
import pickle

import gtsam
import numpy as np
import pytest

from tests.backend import _synth as S
from vslam.backend.ba import BackendConfig, BAProblem, BAResult, local_bundle_adjustment
from vslam.backend.factors import FactorBuilder, FactorCache, L, X, symbol_keys
from vslam.backend.window import dense_window


def _sub(problem: BAProblem, kfs: list[int], fixed: set[int]) -> BAProblem:
    """The observations of keyframes ``kfs`` and the points they see, as a window with ``fixed`` held."""
    keep = np.isin(problem.obs_kf, kfs)
    pts = np.unique(problem.obs_pt[keep]).tolist()
    return BAProblem({k: problem.poses[k] for k in kfs}, set(fixed), {j: problem.points[j] for j in pts},
                     problem.obs_kf[keep], problem.obs_pt[keep], problem.obs_uv[keep], problem.obs_ur[keep])


def _windows() -> list[BAProblem]:
    """Three overlapping windows of one perturbed scene, as consecutive keyframes' local BA would see them."""
    rng = np.random.default_rng(3)
    _, _, prob = S.window(rng, n_kf=8, obs_per_kf=120)
    prob = S.perturb(rng, prob)
    third = _sub(prob, [3, 4, 5, 6, 7], {3, 4})
    third.obs_uv = third.obs_uv.copy()
    third.obs_uv[::7, 0] += 0.25  # a re-observed keypoint: same (kf, point), other measurement
    return [_sub(prob, [0, 1, 2, 3, 4], {0, 1}), _sub(prob, [1, 2, 3, 4, 5, 6], {1, 2}), third]


def _assert_same(a: BAResult, b: BAResult) -> None:
    assert list(a.poses) == list(b.poses) and list(a.points) == list(b.points)
    for k in a.poses:
        assert a.poses[k].tobytes() == b.poses[k].tobytes()
    for j in a.points:
        assert a.points[j].tobytes() == b.points[j].tobytes()
    assert a.inliers.tobytes() == b.inliers.tobytes()
    assert (a.iterations, repr(a.initial_error), repr(a.final_error)) == (b.iterations, repr(b.initial_error),
                                                                          repr(b.final_error))


@pytest.mark.parametrize("solver", ["gtsam", "numpy"])
def test_cache_gives_the_result_without_it(solver):
    cfg = BackendConfig(solver=solver)
    cache = FactorCache()
    for problem in _windows():
        _assert_same(local_bundle_adjustment(problem, S.CAM, cfg, cache=cache), local_bundle_adjustment(problem, S.CAM, cfg))
    if solver == "numpy":
        assert len(cache) == 0  # the numpy solver builds no factors


def _rows(problem: BAProblem):
    win = dense_window(problem, S.CAM, BackendConfig())
    return win.kf, win.pt, win.meas, win.stereo, win.sigma


def test_cache_reuses_only_identical_rows_and_holds_the_last_window():
    w1, w2, w3 = _windows()
    cache = FactorCache()
    f1 = cache.factors(S.CAM, 1.345, *_rows(w1))
    f2 = cache.factors(S.CAM, 1.345, *_rows(w2))
    assert len(cache) == len(f2)  # bounded: the last window only
    prev = {(int(k), int(j)): f for k, j, f in zip(w1.obs_kf, w1.obs_pt, f1)}
    reused = [prev.get((int(k), int(j))) is f for k, j, f in zip(w2.obs_kf, w2.obs_pt, f2)]
    shared = [(int(k), int(j)) in prev for k, j in zip(w2.obs_kf, w2.obs_pt)]
    assert reused == shared and any(shared) and not all(shared)
    f3 = cache.factors(S.CAM, 1.345, *_rows(w3))
    prev = {(int(k), int(j)): f for k, j, f in zip(w2.obs_kf, w2.obs_pt, f2)}
    moved = np.zeros(len(w3.obs_kf), bool)
    moved[::7] = True
    for k, j, f, m in zip(w3.obs_kf.tolist(), w3.obs_pt.tolist(), f3, moved):
        assert (prev.get((k, j)) is f) == ((k, j) in prev and not m)
    # another Huber threshold (or camera) is another factor: nothing is reused
    f4 = cache.factors(S.CAM, 2.0, *_rows(w3))
    assert not any(a is b for a, b in zip(f3, f4))
    assert len(pickle.loads(pickle.dumps(cache))) == 0  # travels empty (a worker process keeps its own)


def _same_factor(a, b, values: gtsam.Values) -> bool:
    """Equal parameters (GTSAM's ``equals`` is strict: a zero tolerance fails even a factor against itself) and the
    same error bits at ``values``."""
    return a.equals(b, 1e-300) and repr(a.error(values)) == repr(b.error(values))


def _values(problem: BAProblem) -> gtsam.Values:
    v = gtsam.Values()
    for k, T in problem.poses.items():
        v.insert(X(k), gtsam.Pose3(T))
    for j, p in problem.points.items():
        v.insert(L(j), np.asarray(p, np.float64))
    return v


def test_cached_factors_equal_built_ones():
    w1, w2, _ = _windows()
    cache = FactorCache()
    cache.factors(S.CAM, 1.345, *_rows(w1))
    got = cache.factors(S.CAM, 1.345, *_rows(w2))
    want = FactorBuilder(S.CAM, 1.345).factors(*_rows(w2))
    assert len(got) == len(want)
    values = _values(w2)
    assert all(_same_factor(a, b, values) for a, b in zip(got, want))


def test_factors_match_per_row_construction():
    """The vectorised builder makes the factor the per-observation code made (keys, measurement, model)."""
    rgbd = dataclasses.replace(S.CAM, disparity_sigma=0.1)
    rng = np.random.default_rng(0)
    n = 40
    kf, pt = rng.integers(0, 9, n), rng.integers(0, 1000, n)
    meas = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n), rng.uniform(0, 640, n)])
    stereo, sigma = rng.random(n) < 0.5, 1.2 ** rng.integers(0, 3, n)
    values = gtsam.Values()
    for k in range(9):
        values.insert(X(k), gtsam.Pose3(S.camera_path(rng, 1)[0]))
    for j in np.unique(pt).tolist():
        values.insert(L(j), rng.uniform(-1, 1, 3) + [0, 0, 6])
    for cam in (S.CAM, rgbd):
        for T_bc in (None, S.camera_path(rng, 1)[0]):
            b = FactorBuilder(cam, 1.345, T_body_cam=T_bc)
            extra = () if T_bc is None else (gtsam.Pose3(T_bc),)
            for f, k, j, (u, v, r), st, s in zip(b.factors(kf, pt, meas, stereo, sigma), kf.tolist(), pt.tolist(),
                                                 meas.tolist(), stereo.tolist(), sigma.tolist()):
                if st:
                    ref = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, r, v), b.noise(3, s), X(k), L(j),
                                                      b.K_stereo, *extra)
                else:
                    ref = gtsam.GenericProjectionFactorCal3_S2(np.array([u, v]), b.noise(2, s), X(k), L(j),
                                                               b.K_mono, *extra)
                assert _same_factor(f, ref, values)


def test_symbol_keys():
    ids = np.array([0, 1, 7, 123456, (1 << 40) + 3])
    assert symbol_keys("x", ids) == [X(i) for i in ids.tolist()]
    assert symbol_keys("l", ids) == [L(i) for i in ids.tolist()]
    assert symbol_keys("x", np.zeros(0, np.int64)) == []


def test_dense_window_points_in_any_order():
    w, _, _ = _windows()
    shuffled = dataclasses.replace(w, points=dict(reversed(list(w.points.items()))))
    a, b = dense_window(w, S.CAM, BackendConfig()), dense_window(shuffled, S.CAM, BackendConfig())
    assert a.pt_ids.tobytes() == b.pt_ids.tobytes() and a.P0.tobytes() == b.P0.tobytes()
    assert a.ip.tobytes() == b.ip.tobytes()
    assert np.all(np.diff(a.pt_ids) > 0)
