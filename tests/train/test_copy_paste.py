"""Copy-paste augmentation: a pasted person's box is the box of its visible pixels, hidden pastes are dropped,
and the benchmark's walkers never reach the detector's training data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vslam.paths import data_root
from vslam.train.copy_paste import crop_background, paste, tilted
from vslam.train.detector_data import Sample

COCO = data_root() / "coco128"
TEDDY = data_root() / "tum" / "rgbd_dataset_freiburg3_teddy"


def _cutout(h: int, w: int, colour: int = 200) -> np.ndarray:
    """A BGRA cutout whose opaque part is an ellipse (the box of the alpha is tighter than the crop)."""
    import cv2

    a = np.zeros((h, w), np.uint8)
    cv2.ellipse(a, (w // 2, h // 2), (w // 2 - 2, h // 2 - 2), 0, 0, 360, 255, -1)
    return np.dstack([np.full((h, w, 3), colour, np.uint8), a])


def test_pasted_box_is_the_box_of_visible_pixels():
    bg = Sample(np.zeros((120, 160, 3), np.uint8), np.array([[5.0, 5, 20, 20]]), np.array([1]))
    for seed in range(10):
        s = paste(bg, [_cutout(60, 24)], label=0, rng=np.random.default_rng(seed), n=1)
        np.testing.assert_array_equal(s.boxes[0], bg.boxes[0])  # the background's labels are kept
        assert s.labels[0] == 1 and set(s.labels[1:].tolist()) <= {0}
        if len(s.boxes) == 1:
            continue  # mostly outside the canvas: dropped
        x1, y1, x2, y2 = s.boxes[1].astype(int)
        lit = np.nonzero(s.image[..., 0] >= 0.5 * s.image.max())  # at least half opaque (the edge is feathered)
        assert abs(lit[1].min() - x1) <= 1 and abs(lit[1].max() + 1 - x2) <= 1
        assert abs(lit[0].min() - y1) <= 1 and abs(lit[0].max() + 1 - y2) <= 1


class SameRng:
    """An rng that always draws the same place and size."""

    def integers(self, lo, hi=None):
        return 0 if hi is None else lo + (hi - lo) // 2

    def uniform(self, lo, hi):
        return (lo + hi) / 2

    def random(self):
        return 0.9


def test_a_paste_hidden_by_a_later_one_is_dropped():
    """Two identical cutouts at the same place: the second hides the first, so only one box survives."""

    bg = Sample(np.zeros((120, 160, 3), np.uint8), np.zeros((0, 4)), np.zeros(0, np.int64))
    s = paste(bg, [_cutout(60, 24)], label=0, rng=SameRng(), n=2)  # type: ignore[arg-type]
    assert len(s.boxes) == 1 and s.labels.tolist() == [0]


def test_closeup_pastes_are_taller_than_the_frame_and_cut_by_it():
    """closeup=1: every person is 1-2 image heights tall, so its box spans the frame's height (cut at the top, the
    bottom or both); without close-ups no person is taller than 0.95 of the frame."""
    bg = Sample(np.zeros((120, 160, 3), np.uint8), np.zeros((0, 4)), np.zeros(0, np.int64))
    kept = 0
    for seed in range(20):
        s = paste(bg, [_cutout(60, 24)], label=0, rng=np.random.default_rng(seed), n=1, closeup=1.0)
        for x1, y1, x2, y2 in s.boxes:
            kept += 1
            assert y2 - y1 >= 0.7 * 120 and (y1 <= 1 or y2 >= 119)
    assert kept >= 15
    for seed in range(20):
        s = paste(bg, [_cutout(60, 24)], label=0, rng=np.random.default_rng(seed), n=1)
        assert all(y2 - y1 <= 0.95 * 120 + 1 for _, y1, _, y2 in s.boxes)


def test_tilted_cutout_keeps_all_of_the_person():
    """A 90-degree tilt turns a 60x24 upright person into a 24x60 lying one: same opaque area, nothing cut."""
    cut = _cutout(60, 24)
    t = tilted(cut, 90.0)
    assert t.shape[:2] == (24, 60)
    assert abs(int((t[..., 3] >= 128).sum()) - int((cut[..., 3] >= 128).sum())) <= 0.03 * (cut[..., 3] >= 128).sum()
    t = tilted(cut, 20.0)
    ys, xs = np.nonzero(t[..., 3] >= 128)
    assert ys.min() > 0 and xs.min() > 0 and ys.max() < t.shape[0] - 1 and xs.max() < t.shape[1] - 1


def test_occluded_pastes_are_labelled_by_what_is_left_visible():
    """occluded=1 on a textured background: part of every kept person is covered by scene texture, and the box
    is still the box of its visible pixels (smaller than the box of the person pasted without occlusion)."""
    rng = np.random.default_rng(0)
    bg = Sample(rng.integers(0, 100, (120, 160, 3), dtype=np.uint8), np.zeros((0, 4)), np.zeros(0, np.int64))
    smaller = 0
    for seed in range(20):
        plain = paste(bg, [_cutout(60, 24, 255)], label=0, rng=np.random.default_rng(seed), n=1)
        hid = paste(bg, [_cutout(60, 24, 255)], label=0, rng=np.random.default_rng(seed), n=1, occluded=1.0)
        lit = hid.image[..., 0] >= 115  # the cutout is >= 127 (gain >= 0.5) on a background below 100
        if len(hid.boxes) == 0:
            continue
        x1, y1, x2, y2 = hid.boxes[0].astype(int)
        ys, xs = np.nonzero(lit)
        off = max(abs(xs.min() - x1), abs(xs.max() + 1 - x2), abs(ys.min() - y1), abs(ys.max() + 1 - y2))
        assert off <= 2  # the feathered edge
        assert lit.sum() < 0.75 * (plain.image[..., 0] >= 115).sum()
        px1, py1, px2, py2 = plain.boxes[0]
        smaller += int((x2 - x1) * (y2 - y1) < 0.95 * (px2 - px1) * (py2 - py1))
    assert smaller >= 8


def test_crop_background_keeps_at_most_four_thirds():
    wide = np.zeros((370, 1226, 3), np.uint8)
    c = crop_background(wide, np.random.default_rng(0))
    assert c.shape == (370, 493, 3)
    assert crop_background(np.zeros((480, 640, 3), np.uint8), np.random.default_rng(0)).shape == (480, 640, 3)


@pytest.mark.skipif(not (COCO.is_dir() and TEDDY.is_dir()), reason="COCO128 / TUM teddy not in $VSLAM_DATA")
def test_benchmark_walkers_are_held_out_of_training():
    from vslam.data.composite import benchmark_stems, person_cutouts, person_instances
    from vslam.train.detector import TrainConfig, training_data

    stems = benchmark_stems(COCO)
    walkers = person_cutouts(COCO)
    assert 1 <= len(stems) <= len(walkers) == 20
    cfg = TrainConfig(classes=("person", "car"), coco=str(COCO), copy_paste=0.5, synthetic_seeds=(), img_size=128)
    data = training_data(cfg)
    n_train = len(list((COCO / "images" / "train2017").glob("*.jpg")))
    assert len(data.samples) == n_train - len(stems)
    kept = person_instances(COCO, min_height_px=48, min_aspect=0.0, whole=False, exclude=stems)
    assert {s for s, _ in kept}.isdisjoint(stems) and len(data.cutouts) == len(kept)
    for w in walkers:  # no training cutout is one of the benchmark's walkers
        assert not any(c.shape == w.shape and np.array_equal(c, w) for c in data.cutouts)
    # without copy-paste or the composite evaluation, the recipe of the first model: every train image
    plain = training_data(dataclasses.replace(cfg, copy_paste=0.0))
    assert len(plain.samples) == n_train and not plain.cutouts
