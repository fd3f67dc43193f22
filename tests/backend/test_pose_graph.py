"""Pose-graph optimisation: a loop edge removes drift injected into the odometry chain."""

from __future__ import annotations

import numpy as np

from vslam.backend.pose_graph import PoseEdge, PoseGraphConfig, optimize_pose_graph
from vslam.geometry.se3 import inv_T, make_T, so3_exp


def _circle(n: int, radius: float = 2.0) -> list[np.ndarray]:
    """n camera poses on a horizontal circle, looking along the tangent, last one next to the first."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        out.append(make_T(so3_exp(np.array([0.0, a, 0.0])), np.array([radius * np.sin(a), 0.0, radius * np.cos(a)])))
    return out


def _drifted(true: list[np.ndarray], rng: np.random.Generator) -> list[np.ndarray]:
    """Compose the true relative motions with a constant yaw bias and noise: the odometry's drift."""
    est = [true[0].copy()]
    bias = make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.array([0.004, 0.0, 0.0]))
    for a, b in zip(true[:-1], true[1:]):
        noise = make_T(so3_exp(rng.normal(0, 1e-3, 3)), rng.normal(0, 1e-3, 3))
        est.append(est[-1] @ inv_T(a) @ b @ bias @ noise)
    return est


def _ate(a: dict[int, np.ndarray], b: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((a[k][:3, 3] - b[k][:3, 3]) ** 2) for k in a])))


def test_loop_edge_removes_injected_drift():
    true = _circle(40)
    est = _drifted(true, np.random.default_rng(0))
    poses = dict(enumerate(est))
    edges = [PoseEdge(k, k + 1, inv_T(est[k]) @ est[k + 1]) for k in range(39)]
    loop = PoseEdge(0, 39, inv_T(true[0]) @ true[39], loop=True)  # a verified loop measures the truth
    before = _ate(poses, true)
    after, e0, e1 = optimize_pose_graph(poses, edges + [loop], {0})
    assert before > 0.15  # the injected drift is large: measured 0.50 m
    assert _ate(after, true) < 0.1 * before  # measured 0.035 m
    assert e1 < 0.01 * e0  # the biased odometry cannot agree with the loop exactly: measured 0.5 %
    np.testing.assert_array_equal(after[0], est[0])  # the fixed keyframe is returned bit for bit


def test_without_loop_nothing_moves_and_isolated_keyframes_are_kept():
    true = _circle(10)
    est = _drifted(true, np.random.default_rng(1))
    poses = dict(enumerate(est))
    poses[99] = np.eye(4)  # no edge touches it
    edges = [PoseEdge(k, k + 1, inv_T(est[k]) @ est[k + 1]) for k in range(9)]
    after, _, _ = optimize_pose_graph(poses, edges, {0})
    for k in range(10):
        np.testing.assert_allclose(after[k], est[k], atol=1e-7)
    np.testing.assert_array_equal(after[99], np.eye(4))


def test_robust_kernel_limits_a_wrong_loop():
    """With cauchy_k > 0 a grossly wrong loop edge bends the chain far less than plain least squares."""
    true = _circle(20)
    poses = dict(enumerate(true))
    edges = [PoseEdge(k, k + 1, inv_T(true[k]) @ true[k + 1]) for k in range(19)]
    wrong = PoseEdge(0, 19, make_T(np.eye(3), np.array([3.0, 0.0, 0.0])), loop=True)
    plain, _, _ = optimize_pose_graph(poses, edges + [wrong], {0})
    robust, _, _ = optimize_pose_graph(poses, edges + [wrong], {0}, PoseGraphConfig(cauchy_k=1.0))
    assert _ate(robust, true) < 0.05 * _ate(plain, true)  # measured 0.002 vs 1.86 m


def test_sim3_loop_edge_removes_injected_scale_drift():
    """Monocular drift: each step's translation 1 % shorter than the last (scale drift) + the yaw bias. An SE3
    graph cannot undo a scale drift; the Sim3 graph with the loop's measured scale does."""
    from vslam.backend.pose_graph import SimEdge, optimize_sim3_graph, sim_matrix, sim_parts

    true = _circle(40)
    rng = np.random.default_rng(0)
    est, scale = [true[0].copy()], [1.0]
    bias = make_T(so3_exp(np.array([0.0, 0.01, 0.0])), np.zeros(3))
    for a, b in zip(true[:-1], true[1:]):
        scale.append(scale[-1] * 0.99)
        rel = inv_T(a) @ b @ bias @ make_T(so3_exp(rng.normal(0, 1e-3, 3)), rng.normal(0, 1e-3, 3))
        rel[:3, 3] *= scale[-1]
        est.append(est[-1] @ rel)
    S = {k: sim_matrix(T) for k, T in enumerate(est)}
    edges = [SimEdge(k, k + 1, np.linalg.inv(S[k]) @ S[k + 1]) for k in range(39)]
    # the loop measures keyframe 39 in keyframe 0's frame at the scale of the start: true pose, scale 1 / scale[39]
    loop = SimEdge(0, 39, sim_matrix(inv_T(true[0]) @ true[39], 1.0 / scale[-1]), loop=True)
    before = _ate(dict(enumerate(est)), true)
    after, e0, e1 = optimize_sim3_graph(S, edges + [loop], {0})
    poses = {k: make_T(*sim_parts(M)[:2]) for k, M in after.items()}
    assert before > 0.3  # measured 0.65 m
    assert _ate(poses, true) < 0.1 * before  # measured 0.041 m
    assert abs(sim_parts(after[39])[2] * scale[-1] - 1) < 0.05  # keyframe 39's scale correction ~ 1 / 0.68 (0.99)
    se3_after, _, _ = optimize_pose_graph(dict(enumerate(est)), [PoseEdge(e.i, e.j, inv_T(est[e.i]) @ est[e.j]) for e in edges]
                                          + [PoseEdge(0, 39, inv_T(true[0]) @ true[39], loop=True)], {0})
    assert _ate(poses, true) < 0.5 * _ate(se3_after, true)  # the rigid graph leaves the scale error (0.53 m)
    np.testing.assert_array_equal(after[0], S[0])
