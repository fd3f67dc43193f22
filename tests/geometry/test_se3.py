import numpy as np

from vslam.geometry import R_to_quat_wxyz, inv_T, make_T, quat_wxyz_to_R, so3_exp, so3_log
from vslam.geometry.se3 import gather_Rt


def test_inverse_and_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        R = so3_exp(rng.normal(size=3))
        T = make_T(R, rng.normal(size=3))
        np.testing.assert_allclose(T @ inv_T(T), np.eye(4), atol=1e-12)
        q = R_to_quat_wxyz(R)
        assert q[0] >= 0
        np.testing.assert_allclose(quat_wxyz_to_R(q), R, atol=1e-12)
        np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-12)


def test_quaternion_order_is_wxyz():
    # 90 deg about z: (w, x, y, z) = (cos45, 0, 0, sin45)
    R = quat_wxyz_to_R(np.array([np.sqrt(0.5), 0, 0, np.sqrt(0.5)]))
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_inverse_of_stack():
    Ts = np.stack([make_T(so3_exp([0, 0, a]), [a, 1, 2]) for a in (0.1, 0.2, 0.3)])
    np.testing.assert_allclose(np.einsum("nij,njk->nik", Ts, inv_T(Ts)), np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)


def test_gather_Rt_equals_fancy_indexing():
    rng = np.random.default_rng(0)
    T = rng.normal(size=(5, 4, 4))
    idx = np.array([4, 0, 0, 2, 3, 4])
    R, t = gather_Rt(T, idx)
    np.testing.assert_array_equal(R, T[idx, :3, :3])
    np.testing.assert_array_equal(t, T[idx, :3, 3])


def test_interpolate_poses_fills_unknown_between_known_of_the_same_group():
    from vslam.geometry.se3 import interpolate_poses, make_T, so3_exp

    t = np.arange(6, dtype=float)
    T = np.array([make_T(so3_exp(np.array([0, 0, 0.1 * k])), np.array([k, 0.0, 0.0])) for k in range(6)])
    T_bad = T.copy()
    T_bad[[2, 3], :3, 3] = 99.0  # predicted, wrong
    known = np.array([1, 1, 0, 0, 1, 0], bool)
    out, done = interpolate_poses(t, T_bad, known)
    assert done.tolist() == [False, False, True, True, False, False]  # the last has no known pose after it
    np.testing.assert_allclose(out[[2, 3]], T[[2, 3]], atol=1e-12)  # linear motion: exactly recovered
    np.testing.assert_array_equal(out[5], T_bad[5])
    _, done = interpolate_poses(t, T_bad, known, group=np.array([0, 0, 0, 1, 1, 1]))
    assert done.tolist() == [False, False, False, False, False, False]  # neighbours in another map: left alone


def test_interpolate_poses_follows_a_turn_across_a_long_gap():
    """A camera on a circle (1 m radius, 0.5 rad/s) at 30 Hz loses 3 s: the Hermite curve through the measured
    motion at both ends stays within ~1 cm of the arc; the chord (linear) cuts it by 0.27 m."""
    from vslam.geometry.se3 import interpolate_poses, make_T, so3_exp

    t = np.arange(0, 6, 1 / 30)
    ang = 0.5 * t
    T = np.array([make_T(so3_exp(np.array([0, 0, a])), np.array([np.cos(a), np.sin(a), 0.0])) for a in ang])
    known = ~((t > 1.5) & (t < 4.5))
    out, done = interpolate_poses(t, T, known)
    assert done.sum() == (~known).sum()
    err = np.linalg.norm(out[~known, :3, 3] - T[~known, :3, 3], axis=1)
    assert err.max() < 0.02, err.max()  # a cubic on an 86 degree arc: ~1 cm
    np.testing.assert_allclose(out[~known, :3, :3], T[~known, :3, :3], atol=1e-9)  # constant rate: slerp exact
    lin, _ = interpolate_poses(t, T, known, tangent_window=0.0)  # no tangent: the chord
    assert np.linalg.norm(lin[~known, :3, 3] - T[~known, :3, 3], axis=1).max() > 0.1


def test_adjoint_moves_a_perturbation_across_the_pose():
    """T Exp(x) T^-1 = Exp(adjoint(T) x), in (rotation, translation) order as GTSAM's Pose3.AdjointMap."""
    from scipy.linalg import expm

    from vslam.geometry.se3 import adjoint, inv_T, make_T, skew, so3_exp

    def hat(x):
        H = np.zeros((4, 4))
        H[:3, :3], H[:3, 3] = skew(x[:3]), x[3:]
        return H

    T = make_T(so3_exp(np.array([0.3, -0.2, 0.5])), np.array([1.0, 2.0, -0.5]))
    x = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.3])
    np.testing.assert_allclose(T @ expm(hat(x)) @ inv_T(T), expm(hat(adjoint(T) @ x)), atol=1e-12)
