"""Filters: exact on linear-Gaussian problems, MCC -> CKF in the limit, robust beats CKF with outliers."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.fusion.filters import (
    AdaptiveRobustConfig, AdaptiveRobustSRCKF, Belief, CubatureKF, ExtendedKF, SquareRootCKF,
    kalman_exact, make_filter, tria,
)


def _linear_problem(rng: np.random.Generator, T: int = 40):
    dt = 0.5
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    Q = np.diag([0.01, 0.01, 0.1, 0.1])
    H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [1.0, 1.0, 0.0, 0.5]])
    R = np.diag([0.5, 0.4, 0.3])
    x = np.zeros(4)
    ys = []
    for _ in range(T):
        x = F @ x + rng.multivariate_normal(np.zeros(4), Q)
        ys.append(H @ x + rng.multivariate_normal(np.zeros(3), R))
    return F, Q, H, R, np.array(ys)


def _run(filt, F, Q, H, R, ys, x0, P0):
    b = Belief.from_cov(x0, P0)
    out_x, out_P = [], []
    for y in ys:
        b = filt.predict(b, lambda X: X @ F.T, Q)
        b, _ = filt.update(b, y, lambda X: X @ H.T, R)
        out_x.append(b.x)
        out_P.append(b.P)
    return np.array(out_x), np.array(out_P)


@pytest.mark.parametrize("filt", [ExtendedKF(), CubatureKF(), SquareRootCKF(),
                                  AdaptiveRobustSRCKF(AdaptiveRobustConfig(kernel_sigma=np.inf, fading=False))])
def test_linear_gaussian_matches_exact_kf(filt):
    F, Q, H, R, ys = _linear_problem(np.random.default_rng(1))
    x0, P0 = np.array([1.0, -1.0, 0.2, 0.0]), np.diag([2.0, 2.0, 1.0, 1.0])
    xs_ref, Ps_ref = kalman_exact(x0, P0, F, Q, H, R, ys)
    xs, Ps = _run(filt, F, Q, H, R, ys, x0, P0)
    tol = 1e-6 if isinstance(filt, ExtendedKF) else 1e-8  # EKF uses numerical Jacobians
    np.testing.assert_allclose(xs, xs_ref, atol=tol)
    np.testing.assert_allclose(Ps, Ps_ref, atol=tol)


def test_huge_kernel_reduces_mcc_to_ckf():
    F, Q, H, R, ys = _linear_problem(np.random.default_rng(2))
    ys[5] += 50.0  # an outlier: the CKF follows it, and so must MCC with an infinite-ish kernel
    x0, P0 = np.zeros(4), np.eye(4)
    xs_ckf, _ = _run(CubatureKF(), F, Q, H, R, ys, x0, P0)
    wide = AdaptiveRobustSRCKF(AdaptiveRobustConfig(kernel_sigma=1e7, fading=False))
    xs_mcc, _ = _run(wide, F, Q, H, R, ys, x0, P0)
    np.testing.assert_allclose(xs_mcc, xs_ckf, atol=1e-8)
    narrow = AdaptiveRobustSRCKF(AdaptiveRobustConfig(kernel_sigma=2.0, fading=False))
    xs_narrow, _ = _run(narrow, F, Q, H, R, ys, x0, P0)
    assert np.abs(xs_narrow[5] - xs_ckf[5]).max() > 1.0  # and a narrow kernel does not


def test_fading_factor_inflates_on_model_mismatch():
    # the filter believes Q is tiny while the truth jumps: alpha must exceed 1 after the jump
    filt = AdaptiveRobustSRCKF(AdaptiveRobustConfig(kernel_sigma=np.inf, fading=True))
    b = Belief.from_cov(np.zeros(1), np.eye(1) * 1e-4)
    alphas = []
    for k in range(20):
        b = filt.predict(b, lambda X: X, np.eye(1) * 1e-6)
        b, info = filt.update(b, np.array([5.0 if k >= 10 else 0.0]), lambda X: X, np.eye(1) * 0.01)
        alphas.append(info.alpha)
    assert max(alphas[:10]) < 1.5 and alphas[10] > 100.0


def test_tria_reproduces_product():
    A = np.random.default_rng(0).normal(size=(5, 12))
    S = tria(A)
    np.testing.assert_allclose(S @ S.T, A @ A.T, atol=1e-12)
    assert np.allclose(S, np.tril(S)) and np.all(np.diag(S) > 0)


def _contaminated_rmse(seed: int, names: list[str]) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    F, Q, H, R, _ = _linear_problem(rng, 1)
    T = 150
    x = np.zeros(4)
    xs, ys = [], []
    for _ in range(T):
        x = F @ x + rng.multivariate_normal(np.zeros(4), Q)
        e = rng.multivariate_normal(np.zeros(3), R)
        hit = rng.random(3) < 0.10
        e[hit] += rng.normal(0, 30.0, hit.sum())  # 10 % gross errors (multipath-like)
        xs.append(x)
        ys.append(H @ x + e)
    xs = np.array(xs)
    out = {}
    for n in names:
        est, _ = _run(make_filter(n), F, Q, H, R, np.array(ys), np.zeros(4), np.eye(4))
        out[n] = float(np.sqrt(np.mean(np.sum((est[:, :2] - xs[:, :2]) ** 2, axis=1))))
    return out


def test_robust_beats_ckf_with_outliers():
    res = [_contaminated_rmse(s, ["ckf", "arsckf"]) for s in range(8)]
    ckf = np.mean([r["ckf"] for r in res])
    rob = np.mean([r["arsckf"] for r in res])
    assert rob < 0.7 * ckf, (rob, ckf)
    assert sum(r["arsckf"] < r["ckf"] for r in res) >= 7
