"""LSD segments, the band descriptor and guided line matching on a synthetic image with a known shift."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig
from vslam.data.synthetic.sequence import SyntheticSequence
from vslam.features.lines import LineConfig, LineExtractor, match_lines, suppress_duplicates

SHIFT = np.array([7.3, -4.1])


@pytest.fixture(scope="module")
def two_images():
    seq = SyntheticSequence(SyntheticConfig(n_frames=2, n_movers=0, markers=False))
    img = seq.frame(0).image
    M = np.float32([[1, 0, SHIFT[0]], [0, 1, SHIFT[1]]])
    return img, cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REPLICATE), seq.calibration.cam0


def test_detect_filters_and_orients(two_images):
    img, _, cam = two_images
    cfg = LineConfig(min_length_px=30.0, max_lines=80)
    lf = LineExtractor(cfg).detect(img, cam)
    assert 30 <= len(lf) <= 80
    assert lf.length.min() >= 30.0 - 1e-6 and np.all(np.diff(lf.length) <= 1e-6)  # longest first
    np.testing.assert_allclose(np.linalg.norm(lf.desc, axis=1), 1.0, atol=1e-5)
    # orientation: the gradient across each segment points along its right-hand normal
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    gx, gy = cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1)
    mid = 0.5 * (lf.segs[:, :2] + lf.segs[:, 2:])
    d = lf.segs[:, 2:] - lf.segs[:, :2]
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / lf.length[:, None]
    ix = np.round(mid).astype(int)
    g = np.stack([gx[ix[:, 1], ix[:, 0]], gy[ix[:, 1], ix[:, 0]]], axis=1)
    assert np.mean(np.sum(g * nrm, axis=1) > 0) > 0.9


def test_guided_matching_recovers_shifted_segments(two_images):
    img, img2, cam = two_images
    ex = LineExtractor(LineConfig())
    a, b = ex.detect(img, cam), ex.detect(img2, cam)
    pred = a.segs + np.tile(SHIFT, 2)
    m = match_lines(pred, a.desc, b, LineConfig())
    assert len(m) >= 0.7 * len(a)
    # every match lies on its prediction (both end points within 1.5 px of the shifted line)
    p, f = pred[m[:, 0]], b.segs[m[:, 1]]
    d = p[:, 2:] - p[:, :2]
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1, keepdims=True)
    dist = np.maximum(np.abs(np.sum((f[:, :2] - p[:, :2]) * nrm, 1)), np.abs(np.sum((f[:, 2:] - p[:, :2]) * nrm, 1)))
    assert np.median(dist) < 0.5 and np.all(dist < 3.0)
    assert len(np.unique(m[:, 1])) == len(m)
    # the descriptor matters: with shuffled descriptors most candidates are rejected
    perm = np.random.default_rng(0).permutation(len(a))
    assert len(match_lines(pred, a.desc[perm], b, LineConfig())) < 0.5 * len(m)


def test_suppress_duplicates_drops_parallel_twin_only():
    raw = np.array([[0, 0, 100, 0], [10, 1, 60, 1], [10, 30, 60, 30], [0, 0, 0, 80.0]])
    out = suppress_duplicates(raw)
    np.testing.assert_array_equal(out, raw[[0, 2, 3]])
