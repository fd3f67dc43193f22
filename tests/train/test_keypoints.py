"""ConvPoint training pieces: synthetic shapes, homographies, targets, losses and a toy run (issue 4)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from vslam.errors import ConfigError
from vslam.eval.homography import (
    illumination_change,
    photometric,
    random_homography,
    valid_mask,
    warp,
    warp_points,
)
from vslam.train.keypoints import (
    KeypointTrainConfig,
    cell_targets,
    descriptor_loss,
    detector_loss,
    pseudo_labels,
    train,
)
from vslam.train.shapes import render_shapes


def test_shapes_are_seeded_and_corners_lie_on_edges():
    a, ca = render_shapes(np.random.default_rng(5), 120, 160)
    b, cb = render_shapes(np.random.default_rng(5), 120, 160)
    assert np.array_equal(a, b) and np.array_equal(ca, cb)
    n_total, n_edgy = 0, 0
    for seed in range(20):
        im, corners = render_shapes(np.random.default_rng(seed), 120, 160)
        assert im.dtype == np.uint8 and im.shape == (120, 160)
        gy, gx = np.gradient(im.astype(np.float64))
        g = np.hypot(gx, gy)
        for x, y in np.round(corners).astype(int):
            win = g[max(0, y - 2):y + 3, max(0, x - 2):x + 3]
            n_total += 1
            n_edgy += win.max() > 10  # a visible corner sits on an intensity edge
    assert n_total > 100 and n_edgy / n_total > 0.9


def test_homography_round_trip_and_valid_mask():
    rng = np.random.default_rng(0)
    H = random_homography(rng, 120, 160)
    xy = rng.uniform([0, 0], [159, 119], (50, 2))
    assert np.allclose(warp_points(np.linalg.inv(H), warp_points(H, xy)), xy, atol=1e-9)
    im = np.full((120, 160), 200, np.uint8)
    b, m = warp(im, H), valid_mask(H, 120, 160, erode=1)
    assert (b[m] > 150).all() and m.mean() > 0.4


def test_photometric_changes_keep_type_and_size():
    rng = np.random.default_rng(0)
    im, _ = render_shapes(rng, 64, 80)
    for out in (photometric(im, rng), illumination_change(im, rng)):
        assert out.dtype == np.uint8 and out.shape == im.shape and not np.array_equal(out, im)


def test_cell_targets():
    t = cell_targets(np.array([[3.0, 2.0], [9.4, 8.6], [-1.0, 5.0]]), 16, 24, np.random.default_rng(0))
    assert t.shape == (2, 3)
    assert t[0, 0] == 2 * 8 + 3 and t[1, 1] == 1 * 8 + 1  # (9, 9) -> cell (1,1), in-cell (1,1)
    assert (t == 64).sum() == 4  # the other cells and the point outside: "no keypoint"


def test_detector_loss_is_low_for_the_right_cells_and_ignores_invalid_ones():
    target = torch.tensor([[[5, 64], [64, 12]]])
    good = torch.full((1, 65, 2, 2), -5.0)
    for (i, j), c in np.ndenumerate(target[0].numpy()):
        good[0, c, i, j] = 5.0
    bad = -good
    assert detector_loss(good, target) < 0.01 < 5 < detector_loss(bad, target)
    valid = torch.tensor([[[True, False], [False, False]]])
    bad2 = good.clone()
    bad2[0, :, 1, 1] = -good[0, :, 1, 1]
    assert detector_loss(bad2, target, valid) == pytest.approx(detector_loss(good, target, valid).item())


def test_descriptor_loss_prefers_matching_descriptors():
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(1, 16, 6, 8), dim=1)
    pts = torch.tensor([[[8 * j + 3.5, 8 * i + 3.5] for i in range(6) for j in range(8)]])
    same = descriptor_loss(d, d, pts, pts, [48], 0.1, 4.0)
    other = descriptor_loss(d, torch.nn.functional.normalize(torch.randn(1, 16, 6, 8), dim=1), pts, pts, [48], 0.1, 4.0)
    assert same < 0.1 and other > 2.0


def test_pseudo_labels_pick_the_peaks():
    heat = np.zeros((40, 48), np.float32)
    heat[10, 12], heat[11, 13], heat[30, 30] = 0.9, 0.5, 0.3
    pts = pseudo_labels(heat, 0.2, 2, 10)
    assert pts.tolist() == [[12.0, 10.0], [30.0, 30.0]]


def test_config_checks_are_one_line():
    with pytest.raises(ConfigError, match="multiples of 8"):
        KeypointTrainConfig(size=(100, 120))


def test_toy_training_reduces_both_losses_and_resumes(tmp_path, monkeypatch):
    """The toy recipe with 100 shapes and 80 joint steps (the toy's 60 and 40 left the shapes loss at 0.77-0.81 of
    its start by seed against the bound 0.8, and the descriptor loss fell as far, 0.84-1.14, with the descriptor
    not trained at all). Catches a detector or descriptor loss that does not train (wrong sign, a broken
    gradient, the descriptor term dropped). Measured over seeds 0-9, torch threads 1 and 2, with and without
    torch.use_deterministic_algorithms: shapes loss last/first 0.65-0.72 (untrained, lr 1e-9: 1.00), descriptor
    loss last/first 0.53-0.76 and last 1.59-2.50 (descriptor term off: 0.96-1.22 and 3.35-5.34; chance ln 32 =
    3.47)."""
    import dataclasses
    import math

    import vslam.train.keypoints as tk

    toy = tk.toy_config
    monkeypatch.setattr(tk, "toy_config", lambda cfg: dataclasses.replace(toy(cfg), shapes_steps=100, joint_steps=80))
    m = train(KeypointTrainConfig(out=str(tmp_path / "kp"), toy=True, threads=1))
    loss = m["loss"]
    assert loss["shapes"]["last"] < 0.85 * loss["shapes"]["first"], loss["shapes"]
    assert loss["joint_desc"]["last"] < 0.85 * loss["joint_desc"]["first"], loss["joint_desc"]
    assert loss["joint_desc"]["last"] < 0.8 * math.log(32), loss["joint_desc"]  # toy desc_points: 32
    assert (tmp_path / "kp" / "model.pt").exists() and (tmp_path / "kp" / "pseudo.npz").exists()
    saved = json.loads((tmp_path / "kp" / "metrics.json").read_text())
    assert saved["parameters"] == m["parameters"]
    again = train(KeypointTrainConfig(out=str(tmp_path / "kp"), toy=True, threads=1, resume=True))
    assert again["loss"] == m["loss"]  # the finished run resumes to the same history
