"""KITTI devkit odometry metric: closed-form answers on synthetic drift, and a sanity check on KITTI 00."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.eval._synth import curvy, line, transformed
from vslam.eval import EvalConfig, evaluate, evaluate_files, kitti_odometry_error
from vslam.geometry.se3 import make_T, so3_exp

LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
N = 1201  # a 1.2 km straight line at 1 m per frame


def _segments(n: int, L: float, step: int = 10) -> tuple[int, int]:
    """(frames spanned m, number of segments) for 1 m spacing.

    The devkit ends a segment at the first frame whose distance exceeds
    dist[first] + L strictly, so with integer distances m = L + 1 frames; a
    segment exists while first + m <= n - 1.
    """
    m = int(L) + 1
    return m, len(range(0, n - m, step))


def _weighted(per_length: dict[float, tuple[float, float, int]]) -> tuple[float, float]:
    n = sum(c for _, _, c in per_length.values())
    return sum(t * c for t, _, c in per_length.values()) / n, sum(r * c for _, r, c in per_length.values()) / n


def test_constant_scale_error_of_one_percent():
    gt = line(N, step=1.0)
    est = line(N, step=1.01)
    metric, reason = kitti_odometry_error(gt.poses, est.poses, LENGTHS, 10)
    assert reason is None and metric is not None
    # Hand computation: every segment's error is 1 % of the distance it spans,
    # m = L + 1 metres, divided by the nominal L.
    expected = {}
    for L in LENGTHS:
        m, count = _segments(N, L)
        expected[L] = (0.01 * m / L * 100.0, 0.0, count)
    for p in metric.per_length:
        t, r, count = expected[p.length]
        assert p.n_segments == count
        assert p.t_rel == pytest.approx(t, abs=1e-6)
        assert p.r_rel == pytest.approx(0.0, abs=1e-6)
    t_all, _ = _weighted(expected)
    assert metric.t_rel == pytest.approx(t_all, abs=1e-6)
    assert metric.t_rel == pytest.approx(1.00, abs=0.01)  # 1 % up to the devkit's one-frame overshoot
    assert metric.r_rel == pytest.approx(0.0, abs=1e-9)
    assert metric.n_segments == sum(c for _, _, c in expected.values())


def test_constant_yaw_rate_drift_matches_closed_form():
    w = 2e-4  # rad of heading drift per frame (per metre)
    gt = line(N, step=1.0)
    step = make_T(so3_exp([0.0, 0.0, w]), [1.0, 0.0, 0.0])
    est = np.empty((N, 4, 4))
    est[0] = np.eye(4)
    for k in range(1, N):
        est[k] = est[k - 1] @ step
    metric, _ = kitti_odometry_error(gt.poses, est, LENGTHS, 10)
    assert metric is not None
    # Over m frames the estimate turns by m*w and travels the chord of a circular
    # arc: p_m = sum_j e^{i j w} = e^{i (m-1) w / 2} sin(m w / 2) / sin(w / 2)
    # (geometric series), while GT travels m along x. The error pose is
    # inv(est_rel) @ gt_rel, so |t_err| = |m - p_m| and its angle is m*w.
    expected = {}
    for L in LENGTHS:
        m, count = _segments(N, L)
        p_m = np.exp(1j * (m - 1) * w / 2) * math.sin(m * w / 2) / math.sin(w / 2)
        expected[L] = (abs(m - p_m) / L * 100.0, math.degrees(m * w) / L * 100.0, count)
    for p in metric.per_length:
        t, r, count = expected[p.length]
        assert p.n_segments == count
        assert p.t_rel == pytest.approx(t, abs=1e-6)
        assert p.r_rel == pytest.approx(r, abs=1e-6)
    t_all, r_all = _weighted(expected)
    assert metric.t_rel == pytest.approx(t_all, abs=1e-6)
    assert metric.r_rel == pytest.approx(r_all, abs=1e-6)


def test_metric_ignores_a_rigid_transform_of_the_whole_estimate():
    gt = curvy(n=800, length_scale=60.0)  # several hundred metres
    est = transformed(gt, make_T(so3_exp([0.3, -0.2, 1.0]), [10.0, -4.0, 2.0]))
    metric, _ = kitti_odometry_error(gt.poses, est.poses, LENGTHS, 10)
    assert metric is not None and metric.n_segments > 0
    assert metric.t_rel == pytest.approx(0.0, abs=1e-9)
    assert metric.r_rel == pytest.approx(0.0, abs=1e-6)  # arccos near 1 limits precision


def test_step_and_lengths_are_configurable():
    gt = line(N)
    metric, _ = kitti_odometry_error(gt.poses, gt.poses, (100.0,), 1)
    assert metric is not None and metric.n_segments == _segments(N, 100.0, 1)[1]
    assert [p.length for p in metric.per_length] == [100.0]


def test_short_trajectory_is_not_applicable_with_a_reason():
    gt = line(51)  # 50 m
    metric, reason = kitti_odometry_error(gt.poses, gt.poses)
    assert metric is None
    assert reason is not None and "not applicable" in reason and "50.0 m" in reason
    res = evaluate(gt, gt, EvalConfig(align="none"))
    assert res.kitti is None and res.kitti_reason == reason
    assert res.to_dict()["kitti"] is None


def test_evaluate_reports_the_unaligned_devkit_metric():
    gt = curvy(n=800, length_scale=60.0)
    est = transformed(gt, make_T(so3_exp([0.0, 0.0, 0.5]), [3.0, 0.0, 0.0]), scale=1.01)
    for align in ("none", "se3", "sim3"):
        res = evaluate(est, gt, EvalConfig(align=align, rpe_deltas=()), by_index=True, seconds=False)
        assert res.kitti is not None and 0.5 < res.kitti.t_rel < 1.05  # the 1 % scale error counts
        assert res.kitti.t_rel == pytest.approx(kitti_odometry_error(gt.poses, est.poses)[0].t_rel, abs=1e-12)


@pytest.mark.realdata
def test_kitti_00_orb_is_plausible(evo_traj_dir):
    res = evaluate_files(evo_traj_dir / "KITTI_00_ORB.txt", evo_traj_dir / "KITTI_00_gt.txt", EvalConfig(rpe_deltas=()))
    k = res.kitti
    assert k is not None and math.isfinite(k.t_rel) and math.isfinite(k.r_rel)
    assert 0.2 < k.t_rel < 5.0
    assert 0.01 < k.r_rel < 5.0  # deg/100 m
    assert k.n_segments > 3000 and [p.length for p in k.per_length] == list(LENGTHS)
