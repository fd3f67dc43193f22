"""The BlazePose-lite mask teacher (vslam.train.mask_teacher): its crop and paste-back geometry on synthetic
input with exact answers, the pseudo-mask cache, and the real network on a real photo (skipped without
ai-edge-litert or the data folder)."""

from __future__ import annotations

import importlib.util

import cv2
import numpy as np
import pytest

from vslam.paths import data_root
from vslam.train.mask_teacher import cached_masks, crop_input, crop_transform, default_teacher_path, paste_logits


def test_crop_is_the_square_around_the_box():
    box = np.array([100.0, 50.0, 160.0, 250.0])  # 60 x 200 px, centre (130, 150)
    A = crop_transform(box, margin=1.2, side=256)
    s = 200 * 1.2
    # the crop's edges are the square's edges: pixel-edge coordinates cx -+ s/2 -> crop edges 0 and 256
    for x_edge, u_edge in ((130 - s / 2, 0.0), (130 + s / 2, 256.0)):
        assert A[0, 0] * (x_edge - 0.5) + A[0, 2] == pytest.approx(u_edge - 0.5)
    for y_edge, v_edge in ((150 - s / 2, 0.0), (150 + s / 2, 256.0)):
        assert A[1, 1] * (y_edge - 0.5) + A[1, 2] == pytest.approx(v_edge - 0.5)


def test_crop_input_is_rgb_in_unit_range_black_outside():
    img = np.zeros((100, 100, 3), np.uint8)
    img[..., 0] = 255  # blue in BGR
    crop = crop_input(img, np.array([0.0, 0.0, 50.0, 100.0]), margin=1.5)
    assert crop.shape == (256, 256, 3) and crop.dtype == np.float32
    assert crop[128, 128].tolist() == pytest.approx([0.0, 0.0, 1.0])  # blue is the last channel in RGB
    assert crop[128, 2].tolist() == [0.0, 0.0, 0.0]  # left of the image: black


def test_paste_back_inverts_the_crop_within_the_box():
    """A logit map made from the crop of a known mask pastes back to that mask (inside the box)."""
    H, W = 240, 320
    truth = np.zeros((H, W), np.uint8)
    cv2.ellipse(truth, (150, 120), (30, 80), 10.0, 0, 360, 1, -1)
    box = np.array([112.0, 36.0, 190.0, 205.0])
    crop = crop_input(np.dstack([truth * 255] * 3), box)
    logits = np.where(crop[..., 0] > 0.5, 8.0, -8.0).astype(np.float32)
    got = paste_logits(logits, box, (H, W))
    want = truth.astype(bool)
    want[:, :112] = want[:, 190:] = False
    want[:36] = want[205:] = False
    assert not got[:, :112].any() and not got[205:].any()  # nothing outside the box
    iou = (got & want).sum() / (got | want).sum()
    assert iou > 0.97


class _FakeTeacher:
    calls = 0

    def masks(self, image, boxes):
        type(self).calls += 1
        out = np.zeros((len(boxes), *image.shape[:2]), bool)
        for i, (x1, y1, x2, y2) in enumerate(np.round(boxes).astype(int)):
            out[i, y1:y2, x1:x2] = True
        return out

    def key(self):
        return "fake"


def test_cache_returns_the_same_masks_without_rerunning(tmp_path):
    img = np.zeros((40, 50, 3), np.uint8)
    boxes = np.array([[5.0, 5.0, 20.0, 30.0], [30.0, 2.0, 45.0, 38.0]])
    t = _FakeTeacher()
    a = cached_masks(t, img, boxes, "img-a", tmp_path)
    b = cached_masks(t, img, boxes, "img-a", tmp_path)
    assert _FakeTeacher.calls == 1 and np.array_equal(a, b) and a.dtype == bool and a.shape == (2, 40, 50)
    cached_masks(t, img, boxes[:1], "img-a", tmp_path)  # other boxes: another entry
    assert _FakeTeacher.calls == 2


@pytest.mark.skipif(importlib.util.find_spec("ai_edge_litert") is None,
                    reason="ai-edge-litert not installed (pip install 'vslam[train]')")
def test_teacher_masks_real_people():
    photo = data_root() / "penn_fudan" / "PennFudanPed"
    if not default_teacher_path().is_file() or not photo.is_dir():
        pytest.skip(f"BlazePose-lite or Penn-Fudan not found under {data_root()} (set VSLAM_DATA)")
    from vslam.train.mask_teacher import BlazePoseTeacher
    from vslam.train.photos import load_penn_fudan

    rec = load_penn_fudan(photo, "val", ("person",))[0]
    img, gm = rec.image(), rec.masks()
    pm = BlazePoseTeacher(threads=1).masks(img, rec.boxes)
    assert pm.shape == gm.shape and pm.dtype == bool
    ious = [(a & b).sum() / (a | b).sum() for a, b in zip(pm, gm)]
    assert np.mean(ious) > 0.75  # the whole box as mask scores ~0.5
