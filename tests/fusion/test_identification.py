"""Hypothesis bank (seed 002): convergence to the true channel and the channel-count trade-off."""

from __future__ import annotations

import numpy as np

from vslam.fusion.identification import IdentConfig, bank_statistics, run_bank, slepian_noise


def test_bank_converges_to_true_channel():
    cfg = IdentConfig(n_channels=21)
    for j in (0, 7, 20):
        h = run_bank(cfg, j, np.random.default_rng(j))
        assert np.argmax(h[-1]) == j and h[-1, j] > 0.99
        np.testing.assert_allclose(h.sum(axis=1), 1.0)


def test_more_channels_lower_posterior_and_slower():
    rng = np.random.default_rng(0)
    s21 = bank_statistics(IdentConfig(n_channels=21), 20, rng)
    s71 = bank_statistics(IdentConfig(n_channels=71), 20, rng)
    s601 = bank_statistics(IdentConfig(n_channels=601), 10, rng)
    assert s21.max_post[45] > 0.99 and s601.max_post[45] < 0.7  # seed: 0.999 and 0.45
    assert 3 <= s21.steps_to[0.9] <= 8 and 12 <= s71.steps_to[0.9] <= 25  # seed: 5 and 18 steps


def test_slepian_noise_has_triangle_covariance():
    rng = np.random.default_rng(1)
    u = np.array([0.0, 0.25, 0.5, 1.5])
    n = np.array([slepian_noise(u, rng) for _ in range(20000)])
    C = np.cov(n.T)
    np.testing.assert_allclose(np.diag(C), 1.0, atol=0.05)
    assert abs(C[0, 1] - 0.75) < 0.05 and abs(C[0, 2] - 0.5) < 0.05 and abs(C[0, 3]) < 0.05
