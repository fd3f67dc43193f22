"""The box-prompted mask head over YOLOX (vslam.nn.detectors.yolox_masks): shapes, and that adding it changes
nothing of what the box network computes (the boxes must stay the source's bit for bit)."""

from __future__ import annotations

import pytest
import torch

from vslam.errors import ConfigError
from vslam.nn.detectors.yolox import YOLOX
from vslam.nn.detectors.yolox_masks import YOLOXMasks, expand_boxes
from vslam.nn.registry import DETECTORS

SMALL = {"depth": 0.33, "width": 0.125, "classes": ["person", "car"], "input_size": 64}


def _pair() -> tuple[YOLOX, YOLOXMasks]:
    torch.manual_seed(0)
    box = YOLOX(SMALL).eval()
    masks = YOLOXMasks(SMALL).eval()
    res = masks.load_state_dict(box.state_dict(), strict=False)
    assert not res.unexpected_keys and res.missing_keys and all(k.startswith("mask_head.") for k in res.missing_keys)
    return box, masks


def test_box_outputs_bit_identical_with_the_mask_head():
    box, masks = _pair()
    x = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(1)) * 255
    with torch.no_grad():
        a = box({"image": x})
        b = masks({"image": x, "mask_boxes": [torch.tensor([[4.0, 6.0, 40.0, 60.0]]), torch.zeros((0, 4))]})
    for k in ("pred", "logits", "boxes", "scores"):
        assert torch.equal(a[k], b[k]), k


def test_mask_head_shapes():
    _, m = _pair()
    x = torch.rand(2, 3, 64, 64) * 255
    boxes = [torch.tensor([[4.0, 6.0, 40.0, 60.0], [10.0, 10.0, 20.0, 30.0]]), torch.tensor([[0.0, 0.0, 64.0, 64.0]])]
    with torch.no_grad():
        out = m({"image": x, "mask_boxes": boxes})
    side = m.conf["mask"]["side"]
    assert out["mask_logits"].shape == (3, side, side)
    assert out["mask_rois"][:, 0].tolist() == [0.0, 0.0, 1.0]
    assert [f.shape[-1] for f in out["feats"]] == [8, 4, 2]  # strides 8, 16, 32
    torch.testing.assert_close(out["mask_rois"][:, 1:], expand_boxes(torch.cat(boxes), m.conf["mask"]["margin"]))
    assert m.mask_logits(out["feats"], x, torch.zeros((0, 5))).shape == (0, side, side)
    with torch.no_grad():
        assert "mask_logits" not in m({"image": x})  # no prompts, no masks


def test_registry_entry_and_conf_errors():
    m = DETECTORS.build("yolox-nano-masks", {"classes": ["person"], "mask": {"roi": 7, "side": 28}})
    assert isinstance(m, YOLOXMasks) and m.conf["mask"]["side"] == 28 and m.conf["mask"]["margin"] == 0.1
    deeper = DETECTORS.build("yolox-nano-masks", {**SMALL, "mask": {"refine_convs": 2}}).eval()
    with torch.no_grad():
        out = deeper({"image": torch.zeros(1, 3, 64, 64), "mask_boxes": [torch.tensor([[4.0, 6.0, 40.0, 60.0]])]})
    assert out["mask_logits"].shape == (1, 56, 56) and len(deeper.mask_head.more1) == 1
    with pytest.raises(ConfigError, match="threshold must be in"):
        YOLOXMasks({**SMALL, "mask": {"threshold": 1.0}})
    with pytest.raises(ConfigError, match="side must be 4 x roi"):
        YOLOXMasks({**SMALL, "mask": {"roi": 7, "side": 32}})
    with pytest.raises(ConfigError, match="unknown key 'sid'"):
        YOLOXMasks({**SMALL, "mask": {"sid": 28}})


def test_trained_checkpoint_keeps_the_source_boxes():
    """models/yolox_nano_masks.pt: every tensor of the box network is the shipped YOLOX-nano's, bit for bit."""
    from pathlib import Path

    from vslam.nn.checkpoint import load_model

    repo = Path(__file__).resolve().parents[2]
    masks_path, box_path = repo / "models" / "yolox_nano_masks.pt", repo / "vslam" / "models" / "yolox_nano_slam.pt"
    if not masks_path.is_file():
        pytest.skip(f"{masks_path} not found")
    m, ck = load_model(masks_path, DETECTORS)
    b, _ = load_model(box_path, DETECTORS)
    assert ck["arch"] == "yolox-nano-masks" and isinstance(m, YOLOXMasks)
    sm = m.state_dict()
    for k, v in b.state_dict().items():
        assert torch.equal(sm[k], v), k
    assert set(sm) - set(b.state_dict()) == {k for k in sm if k.startswith("mask_head.")}
