"""ConvPoint network, NMS, descriptor sampling, weights files and the SLAM extractor (issue 4)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vslam.data.types import PinholeCamera
from vslam.errors import ConfigError
from vslam.features import FeatureConfig, make_extractor
from vslam.features.convpoint import (
    ConvPointConfig,
    ConvPointNet,
    DetectSettings,
    batch_tensor,
    default_weights,
    detect_batch,
    heatmap,
    load_convpoint,
    nms,
    sample_descriptors,
    save_convpoint,
    subpixel,
)
from vslam.train.shapes import render_shapes

SMALL = ConvPointConfig(channels=(8, 16, 16, 32), desc_dim=32)


def test_output_shapes_and_unit_descriptors():
    torch.manual_seed(0)
    net = ConvPointNet(SMALL).eval()
    with torch.no_grad():
        logits, desc = net(torch.rand(2, 1, 48, 64))
    assert logits.shape == (2, 65, 6, 8) and desc.shape == (2, 32, 6, 8)
    assert torch.allclose(desc.norm(dim=1), torch.ones(2, 6, 8), atol=1e-5)
    heat = heatmap(logits)
    assert heat.shape == (2, 48, 64) and float(heat.min()) >= 0 and float(heat.max()) <= 1


def test_input_is_standardised_so_gain_and_offset_change_nothing():
    torch.manual_seed(0)
    net = ConvPointNet(SMALL).eval()
    x = torch.rand(1, 1, 32, 32)
    with torch.no_grad():
        a, b = net(x), net(0.5 * x + 0.2)
    assert torch.allclose(a[0], b[0], atol=1e-4) and torch.allclose(a[1], b[1], atol=1e-4)


def test_default_shipped_model_is_small_enough():
    n = sum(p.numel() for p in ConvPointNet().parameters())
    assert n <= 1_500_000  # issue 4: <= 1.5 M parameters


def test_nms_keeps_the_maximum_and_spaces_survivors():
    rng = np.random.default_rng(0)
    heat = torch.from_numpy(rng.random((1, 40, 50)).astype(np.float32))
    heat[0, 10, 10] = 2.0
    out = nms(heat, 3)[0].numpy()
    ys, xs = np.nonzero(out)
    assert out[10, 10] == 2.0
    assert all(abs(out[y, x] - heat[0, y, x].item()) == 0 for y, x in zip(ys, xs))
    d = np.maximum(np.abs(xs[:, None] - xs[None]), np.abs(ys[:, None] - ys[None]))
    np.fill_diagonal(d, 99)
    assert d.min() > 3  # no two survivors share a 7x7 window


def test_nms_plateau_keeps_one_pixel():
    heat = torch.zeros(1, 20, 20)
    heat[0, 5:8, 5:8] = 0.5  # a flat 3x3 plateau
    out = nms(heat, 2)[0]
    assert int((out > 0).sum()) == 1 and out[5, 5] == 0.5


def test_sample_descriptors_at_cell_centres_returns_the_cells():
    torch.manual_seed(0)
    desc = torch.nn.functional.normalize(torch.randn(1, 16, 4, 5), dim=1)
    ij = [(0, 0), (3, 4), (2, 1)]
    xy = torch.tensor([[[8 * j + 3.5, 8 * i + 3.5] for i, j in ij]])
    s = sample_descriptors(desc, xy)[0]
    for k, (i, j) in enumerate(ij):
        assert torch.allclose(s[k], desc[0, :, i, j], atol=1e-5)


def test_subpixel_moves_towards_the_heavier_neighbour():
    heat = np.zeros((10, 10))
    heat[5, 5], heat[5, 6] = 1.0, 1.0
    xy = subpixel(heat, np.array([[5.0, 5.0]]))
    assert xy[0] == pytest.approx([5.5, 5.0])


def test_padding_to_multiples_of_eight():
    x, (h, w) = batch_tensor([np.zeros((37, 50), np.uint8)])
    assert x.shape == (1, 1, 40, 56) and (h, w) == (37, 50)


def test_detect_batch_respects_mask_border_and_budget():
    torch.manual_seed(0)
    net = ConvPointNet(SMALL).eval()
    im, _ = render_shapes(np.random.default_rng(1), 96, 128)
    mask = np.zeros((96, 128), bool)
    mask[:, :64] = True
    s = DetectSettings(conf_thresh=0.0, max_keypoints=50, border=8)
    (xy, score, desc), = detect_batch(net, [im], s, masks=[mask])
    assert 0 < len(xy) <= 50 and desc.shape == (len(xy), 32) and desc.dtype == np.float32
    assert (xy[:, 0] >= 63).all() and (xy[:, 0] <= 128 - 8).all() and (xy[:, 1] >= 7).all()
    assert np.all(np.diff(score) <= 0)  # strongest first


def test_weights_round_trip_and_bad_file(tmp_path):
    torch.manual_seed(0)
    net = ConvPointNet(SMALL).eval()
    p = save_convpoint(net, tmp_path / "cp.pt", {"steps": 1})
    back = load_convpoint(p)
    x = torch.rand(1, 1, 32, 32)
    with torch.no_grad():
        assert torch.allclose(net(x)[0], back(x)[0], atol=1e-5)  # same weights (the loaded model runs NHWC)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="bad.pt: not a ConvPoint checkpoint"):
        load_convpoint(bad)
    with pytest.raises(ConfigError, match="weights not found"):
        load_convpoint(tmp_path / "missing.pt")


def test_shipped_weights_load_offline_and_the_extractor_works():
    if not default_weights().exists():
        pytest.fail(f"{default_weights()} is missing: the trained weights must be committed")
    cam = PinholeCamera(160, 120, 200.0, 200.0, 80.0, 60.0)
    ext = make_extractor(FeatureConfig(extractor="convpoint", n_features=200))
    im, _ = render_shapes(np.random.default_rng(3), 120, 160)
    f = ext.detect(im, cam)
    assert ext.descriptor_kind == "float" and 20 <= len(f) <= 200
    assert f.desc.dtype == np.float32 and np.allclose(np.linalg.norm(f.desc, axis=1), 1, atol=1e-4)
    assert np.allclose(f.uv, f.raw) and (f.octave == 0).all()
    mask = np.zeros((120, 160), bool)
    mask[:, 80:] = True
    assert (ext.detect(im, cam, mask).raw[:, 0] < 80).all()
    again = ext.detect(im, cam)
    assert np.array_equal(again.raw, f.raw) and np.array_equal(again.desc, f.desc)  # deterministic


def test_unknown_device_request_is_one_line():
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    with pytest.raises(ConfigError, match="features.device: cuda"):
        make_extractor(FeatureConfig(extractor="convpoint", device="cuda"))


def test_bf16_inference_finds_nearly_the_same_keypoints():
    if not default_weights().exists():
        pytest.fail(f"{default_weights()} is missing")
    model = load_convpoint(default_weights())
    im, _ = render_shapes(np.random.default_rng(4), 240, 320)
    (a, _, da), = detect_batch(model, [im], DetectSettings(max_keypoints=300))
    (b, _, db), = detect_batch(model, [im], DetectSettings(max_keypoints=300, bf16=True))
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    near = d.min(axis=1) <= 1.0
    assert near.mean() > 0.8  # the same corners, up to bf16 rounding of the heatmap
    j = d.argmin(axis=1)[near]
    assert np.median((da[near] * db[j]).sum(axis=1)) > 0.98  # and nearly the same descriptors
