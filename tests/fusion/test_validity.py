"""Limit values, decision rates and the priority-mode choice (seed 000)."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.fusion.validity import (
    ModeEstimate, choose_modes, confidence_interval, decision_rates, quantile_factor, vio_modes,
)


def test_three_sigma_rule():
    assert quantile_factor(0.9973) == pytest.approx(3.0, abs=1e-3)
    lo, hi = confidence_interval(np.array([1.0]), np.array([2.0]), 0.9545)
    assert lo[0] == pytest.approx(-3.0, abs=1e-3) and hi[0] == pytest.approx(5.0, abs=1e-3)


def test_decision_rates_match_theory_on_gaussian_innovations():
    rng = np.random.default_rng(0)
    v = rng.standard_normal(200_000)
    gross = rng.random(v.size) < 0.05
    v[gross] += 5.0
    d = decision_rates(v, gross, 3.0)
    assert d.false_alarm == pytest.approx(0.0027, abs=0.0006)
    assert d.missed == pytest.approx(0.0228, abs=0.004)  # P(|N(5, 1)| <= 3) = Phi(-2)
    d2 = decision_rates(v, gross, 2.0)
    assert d2.false_alarm > d.false_alarm and d2.missed <= d.missed


def test_mode_choice_switches_when_gnss_is_invalid():
    E = 10
    good = np.eye(3)[None].repeat(E, 0)
    gnss = ModeEstimate("GNSS+INS", np.zeros((E, 3)), good.copy(), np.r_[[True] * 4, [False] * 3, [True] * 3])
    vio = ModeEstimate("VIO", np.ones((E, 3)), 5 * good, np.ones(E, bool))
    idx, pos = choose_modes([gnss, vio])
    assert idx.tolist() == [0] * 4 + [1] * 3 + [0] * 3
    np.testing.assert_array_equal(pos[5], np.ones(3))


def test_vio_gnss_reanchors_at_last_valid_fix():
    t = np.arange(5.0)
    vo_p = np.c_[t * 10.0, np.zeros(5), np.zeros(5)]
    gpos = np.c_[t * 10.0 + 1.0, np.zeros(5), np.zeros(5)]
    valid = np.array([True, True, False, False, True])
    vio, vg = vio_modes(t, t, vo_p, gpos, np.eye(3)[None].repeat(5, 0), valid, 0.01, 0.0)
    np.testing.assert_allclose(vg.pos[:, 0], gpos[:, 0])  # anchored track follows the fixes exactly here
    assert vg.cov[3, 0, 0] > vg.cov[2, 0, 0] > vg.cov[1, 0, 0]  # drift since the anchor grows
    np.testing.assert_allclose(vio.pos[:, 0], gpos[0, 0] + vo_p[:, 0])
