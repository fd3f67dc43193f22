"""Local BA in the worker process (``vslam.backend.worker``): same answer as in-process, clear failures."""

from __future__ import annotations

import numpy as np
import pytest

from tests.backend import _synth as S
from vslam.backend.ba import BackendConfig, local_bundle_adjustment
from vslam.backend.worker import BAWorker


def _problem(seed: int):
    rng = np.random.default_rng(seed)
    _, _, prob = S.window(rng, n_kf=5, obs_per_kf=80)
    prob.fixed = {0}
    prob.obs_uv += rng.normal(0.0, 0.5, prob.obs_uv.shape)
    return S.perturb(rng, prob)


def test_worker_solves_exactly_what_local_ba_solves_in_order():
    problems = [_problem(0), _problem(1)]
    worker = BAWorker()
    try:
        for p in problems:  # both in flight at once: results come back in submission order
            worker.submit(p, S.CAM, _cfg())
        for p in problems:
            got, want = worker.result(), local_bundle_adjustment(p, S.CAM, _cfg())
            assert got.poses.keys() == want.poses.keys() and got.points.keys() == want.points.keys()
            for k in want.poses:
                np.testing.assert_array_equal(got.poses[k], want.poses[k])
            for j in want.points:
                np.testing.assert_array_equal(got.points[j], want.points[j])
            np.testing.assert_array_equal(got.inliers, want.inliers)
    finally:
        worker.close()


def _cfg() -> BackendConfig:
    return BackendConfig()


def test_worker_failure_is_raised_where_the_result_is_awaited():
    bad = _problem(2)
    bad.obs_uv = bad.obs_uv[:3]  # fewer measurements than observations
    worker = BAWorker()
    try:
        worker.submit(bad, S.CAM, _cfg())
        with pytest.raises(RuntimeError, match="local BA failed in the worker process"):
            worker.result()
        worker.submit(_problem(3), S.CAM, _cfg())  # the worker survives a failed problem
        assert worker.result().inliers.any()
    finally:
        worker.close()
    with pytest.raises(RuntimeError, match="nothing was submitted"):
        BAWorker().result()


def test_problems_and_results_pickle_compactly_with_the_same_values():
    import pickle

    from vslam.backend.ba import BAResult

    p = _problem(4)
    q = pickle.loads(pickle.dumps(p))
    assert list(q.points) == list(p.points) and q.fixed == p.fixed and q.poses.keys() == p.poses.keys()
    for j in p.points:
        np.testing.assert_array_equal(q.points[j], p.points[j])
    np.testing.assert_array_equal(q.obs_uv, p.obs_uv)
    r = BAResult({}, dict(p.points), np.ones(3, bool), lines={7: np.ones(6)}, depth_only=np.zeros(3, bool))
    data = pickle.dumps(r)
    assert len(data) < 40 * len(p.points) + 2000  # two arrays, not one pickled array per point
    s = pickle.loads(data)
    assert list(s.points) == list(r.points) and s.lines.keys() == {7} and s.depth_only is not None
    empty = pickle.loads(pickle.dumps(BAResult({}, {}, np.zeros(0, bool))))
    assert empty.points == {}
