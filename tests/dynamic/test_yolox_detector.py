"""YoloxDetector with and without a mask head (vslam.dynamic.yolox_detector): masks in the image's pixels where
the checkpoint has a mask head, the same boxes either way, none without one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vslam.dynamic.yolox_detector import YoloxDetector, paste_masks
from vslam.errors import ConfigError
from vslam.nn.detectors.yolox import YOLOX
from vslam.nn.detectors.yolox_masks import YOLOXMasks

SMALL = {"depth": 0.33, "width": 0.125, "classes": ["person"], "input_size": 64}


def _detectors():
    torch.manual_seed(0)
    box = YOLOX(SMALL).eval()
    torch.nn.init.constant_(box.head.obj_preds[0].bias, 5.0)  # random weights: make some anchors score
    masks = YOLOXMasks(SMALL).eval()
    masks.load_state_dict(box.state_dict(), strict=False)
    return YoloxDetector(box, img_size=64, conf=0.3), YoloxDetector(masks, img_size=64, conf=0.3)


def test_masks_of_the_right_shape_and_same_boxes():
    img = np.random.default_rng(0).integers(0, 255, (48, 80, 3)).astype(np.uint8)
    d0, d1 = (d.detect(img) for d in _detectors())
    assert d0.masks is None and d0.mask_px == 0.0
    assert len(d1.boxes) > 0 and np.array_equal(d0.boxes, d1.boxes) and np.array_equal(d0.scores, d1.scores)
    assert d1.masks.shape == (len(d1.boxes), 48, 80) and d1.masks.dtype == bool and d1.mask_px > 0


def test_masks_for_given_boxes():
    _, det = _detectors()
    img = np.full((64, 64), 90, np.uint8)  # grey input works too
    m = det.masks_for(img, np.array([[10.0, 10.0, 30.0, 50.0]]))
    assert m.shape == (1, 64, 64) and m.dtype == bool
    with pytest.raises(ConfigError, match="no mask head"):
        _detectors()[0].masks_for(img, np.zeros((1, 4)))


def test_paste_masks_places_the_map_in_its_region():
    logits = np.full((1, 8, 8), -5.0, np.float32)
    logits[0, :, :4] = 5.0  # left half on
    m, px = paste_masks(logits, np.array([[10.0, 20.0, 26.0, 36.0]]), (50, 40))
    assert px == pytest.approx(2.0)
    want = np.zeros((50, 40), bool)
    want[20:36, 10:18] = True
    assert np.array_equal(m[0], want)
