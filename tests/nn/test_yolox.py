"""The YOLOX-style detector with the public YOLOX-nano weights (vslam.nn.detectors.yolox, vslam.nn.weights.yolox).

The loader is right when our network reproduces Megvii's export run by onnxruntime on real frames; attention
blocks and class slicing are right when they change nothing of what the source computes; the shipped float16
checkpoint is right when it stays within float16 rounding of the source and loads without onnx."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from vslam.dynamic.yolox_detector import YoloxDetector, input_shape, letterbox_top_left
from vslam.errors import ConfigError
from vslam.nn.detectors.coco import COCO80, SLAM_CLASSES
from vslam.nn.registry import DETECTORS
from vslam.nn.weights.yolox import read_onnx_convs
from vslam.paths import data_root

ONNX = data_root() / "pretrained" / "yolox_nano" / "yolox_nano.onnx"
FRAMES = {  # real frames of the three kinds SLAM sees: indoor RGB-D, street (grey), a street photo of people
    "tum": "tum/rgbd_dataset_freiburg3_teddy/rgb/1341841876.589893.png",
    "kitti": "kitti/sequences/07/image_0/000100.png",
    "fudan": "penn_fudan/PennFudanPed/JPEGImages/FudanPed00001.jpg",
}
SHIPPED = Path(__file__).resolve().parents[2] / "vslam" / "models" / "yolox_nano_slam.pt"
need_onnx = pytest.mark.skipif(not ONNX.is_file(), reason=f"public YOLOX-nano weights not found at {ONNX} "
                                                          "(set VSLAM_DATA to the shared data folder)")


def frame(name: str) -> np.ndarray:
    p = data_root() / FRAMES[name]
    if not p.is_file():
        pytest.skip(f"real frame not found at {p} (set VSLAM_DATA)")
    im = cv2.imread(str(p), cv2.IMREAD_COLOR)  # KITTI's grey frame as 3 equal channels
    return im


def as_input(im: np.ndarray, size: tuple[int, int] = (416, 416)) -> torch.Tensor:
    canvas, _ = letterbox_top_left(im, size)
    return torch.from_numpy(canvas).permute(2, 0, 1)[None].float()


@pytest.fixture(scope="module")
def coco_model():
    if not ONNX.is_file():
        pytest.skip(f"public YOLOX-nano weights not found at {ONNX} (set VSLAM_DATA)")
    pytest.importorskip("onnx", reason="the converter reads ONNX initializers (pip install vslam[train])")
    torch.set_num_threads(2)
    return DETECTORS.pretrained("yolox-nano")


@pytest.fixture(scope="module")
def onnx_read_once(coco_model):
    """The converter with the ONNX file parsed once for the module (each conversion still maps every tensor)."""
    import vslam.nn.weights.yolox as wy

    convs = wy.read_onnx_convs(ONNX)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(wy, "read_onnx_convs", lambda path: convs if Path(path) == ONNX else wy.read_onnx_convs(path))
        yield


@pytest.mark.parametrize("name", sorted(FRAMES))
def test_outputs_equal_onnxruntime_on_real_frames(coco_model, name):
    ort = pytest.importorskip("onnxruntime", reason="the reference outputs come from onnxruntime (vslam[teacher])")
    x = as_input(frame(name))
    ref = ort.InferenceSession(str(ONNX), providers=["CPUExecutionProvider"]).run(None, {"images": x.numpy()})[0]
    with torch.no_grad():
        ours = coco_model({"image": x})["pred"].numpy()
    assert ours.shape == ref.shape == (1, 3549, 85)
    # probabilities (objectness, classes: what decides a detection) within 1e-4 (measured <= 2.2e-5). Box values
    # (cell offsets, log sizes) within 5e-4 of a cell (0.016 px at stride 32): there float32 itself is the limit,
    # ours and onnxruntime's each differ from a float64 run of this network by up to 1.8e-4 on KITTI frame 100.
    # A wrong layer, Focus order or BN reading is off by 0.1 and more.
    np.testing.assert_allclose(ours[..., 4:], ref[..., 4:], atol=1e-4, rtol=0)
    np.testing.assert_allclose(ours[..., :4], ref[..., :4], atol=5e-4, rtol=0)
    # each frame holds an object the source finds (the teddy bear, cars, pedestrians): the comparison is not one
    # of two networks that both see nothing
    assert (ref[0, :, 4:5] * ref[0, :, 5:]).max() > 0.3


@pytest.mark.parametrize("attention", ["se", "cbam", "esea"])
def test_attention_starts_as_the_identity(coco_model, onnx_read_once, attention):
    model = DETECTORS.pretrained("yolox-nano", {"attention": attention})
    assert all(float(g.detach().abs().max()) == 0 for n, g in model.named_parameters() if n.endswith(".gate"))
    x = as_input(frame("fudan"), (224, 160))
    with torch.no_grad():
        a, b = model({"image": x}), coco_model({"image": x})
    assert torch.equal(a["pred"], b["pred"]), "a zero gate must leave the source's outputs bit for bit"
    # the gates learn from the first step (else fine-tuning could never switch attention on)
    model.train()
    model({"image": x})["logits"][..., 4].sum().backward()
    gates = [p.grad for n, p in model.named_parameters() if n.endswith(".gate")]
    assert len(gates) == 3 and all(g is not None and float(g.abs().max()) > 0 for g in gates)


def test_class_slicing_keeps_the_coco_rows(coco_model, onnx_read_once):
    sliced = DETECTORS.pretrained("yolox-nano", {"classes": list(SLAM_CLASSES)})
    rows = [COCO80.index(n) for n in SLAM_CLASSES]
    assert rows == [0, 1, 2, 3, 5, 7]
    x = as_input(frame("kitti"), (416, 128))
    with torch.no_grad():
        full, part = coco_model({"image": x}), sliced({"image": x})
    assert part["pred"].shape[-1] == 5 + 6
    np.testing.assert_allclose(part["pred"][..., :5], full["pred"][..., :5], atol=1e-6, rtol=0)
    # a 1x1 conv of 6 rows sums like one of 80 up to the order of the sum
    np.testing.assert_allclose(part["scores"], full["scores"][..., rows], atol=1e-6, rtol=0)


def test_unknown_class_and_missing_onnx_are_one_line_errors(coco_model, monkeypatch):
    with pytest.raises(ConfigError, match="'pedestrian' are not COCO classes"):
        DETECTORS.pretrained("yolox-nano", {"classes": ["person", "pedestrian"]})
    monkeypatch.setitem(sys.modules, "onnx", None)
    with pytest.raises(ConfigError, match=r"pip install vslam\[train\]") as e:
        read_onnx_convs(ONNX)
    assert "\n" not in str(e.value)


def test_wide_input_decodes_like_the_square_one(coco_model):
    """832x256 (a KITTI frame at its aspect): anchors in row-major order per level, x before y; the confident
    boxes equal those of a square 832x832 input holding the same pixels (same scale, more grey below)."""
    im = frame("kitti")
    assert input_shape(im.shape[:2], 1248, wide=True) == (1248, 384)
    assert input_shape(im.shape[:2], 416, wide=False) == (416, 416)
    with torch.no_grad():
        wide = coco_model({"image": as_input(im, (832, 256))})
        square = coco_model({"image": as_input(im, (832, 832))})
    a = 832 * 256 // 64
    assert wide["pred"].shape == (1, a + a // 4 + a // 16, 85)
    # decoding by hand: level 0 anchor (row i, column j) is index i * 104 + j, centre (offset + (j, i)) * 8
    p, i, j = wide["pred"][0], 20, 90
    k = i * (832 // 8) + j
    cx, cy = (p[k, 0] + j) * 8, (p[k, 1] + i) * 8
    np.testing.assert_allclose(wide["boxes"][0, k, :2], [cx - p[k, 2].exp() * 4, cy - p[k, 3].exp() * 4], rtol=1e-6)
    # the same confident detections (cars in frame 100) in both; rows below 256 only change the coarse levels'
    # context near the bottom edge, so boxes agree to a few pixels
    dets = []
    for out in (wide, square):
        s, c = out["scores"][0].max(-1)
        keep = s > 0.5
        dets.append((out["boxes"][0][keep], s[keep]))
    assert len(dets[0][0]) >= 3, "frame 100 of KITTI 07 shows several cars"
    from vslam.nn.ops import box_iou, nms

    a_boxes = dets[0][0][nms(*dets[0], 0.45)]
    b_boxes = dets[1][0][nms(*dets[1], 0.45)]
    assert len(a_boxes) == len(b_boxes)
    assert box_iou(a_boxes, b_boxes).max(1).values.min() > 0.8  # measured 0.89 (a car cut by the left edge)


@pytest.mark.skipif(not SHIPPED.is_file(), reason="the shipped YOLOX checkpoint is not in this tree")
def test_shipped_model_loads_without_onnx_and_matches_the_source(monkeypatch):
    """The committed checkpoint: loadable by load_detector with onnx unavailable (any import of it fails), and
    its SLAM-class probabilities those of the source (float32 weights: the tolerance of the loader test above)."""
    from vslam.dynamic.detector import load_detector

    with monkeypatch.context() as mp:
        mp.setitem(sys.modules, "onnx", None)
        d = load_detector(SHIPPED)
    assert (type(d).__name__, d.img_size, d.names) == ("YoloxDetector", 416, list(SLAM_CLASSES))
    ort = pytest.importorskip("onnxruntime", reason="the reference outputs come from onnxruntime")
    if not ONNX.is_file():
        pytest.skip(f"public YOLOX-nano weights not found at {ONNX}")
    from vslam.nn.checkpoint import load_model

    model, ck = load_model(SHIPPED, DETECTORS)
    assert ck["meta"]["licence"].startswith("Apache-2.0") and "convert-yolox" in ck["meta"]["command"]
    x = as_input(frame("fudan"))
    ref = ort.InferenceSession(str(ONNX), providers=["CPUExecutionProvider"]).run(None, {"images": x.numpy()})[0][0]
    with torch.no_grad():
        ours = model({"image": x})["pred"][0].numpy()
    rows = [5 + COCO80.index(n) for n in SLAM_CLASSES]
    np.testing.assert_allclose(ours[:, 4:], ref[:, [4] + rows], atol=1e-4, rtol=0)


def test_detector_wrapper_boxes_in_image_pixels(coco_model):
    """YoloxDetector: the letterbox scale undone (top-left, no offset), boxes clipped, names from the classes."""
    im = frame("fudan")
    det = YoloxDetector(coco_model, img_size=416, conf=0.5)
    d = det.detect(im)
    people = d.boxes[d.class_names == "person"]
    assert len(people) == 2, "FudanPed00001 shows two pedestrians"
    # their annotated boxes (PennFudanPed/Annotation/FudanPed00001.txt)
    gt = np.array([[160, 182, 302, 431], [420, 171, 535, 486]], float)
    from vslam.nn.ops import box_iou_np

    assert box_iou_np(people, gt).max(0).min() > 0.8
    assert (d.boxes[:, [0, 2]] <= im.shape[1]).all() and (d.boxes >= 0).all()
    # the same at twice the image size: boxes scale with it
    big = cv2.resize(im, (im.shape[1] * 2, im.shape[0] * 2), interpolation=cv2.INTER_LINEAR)
    d2 = YoloxDetector(coco_model, img_size=416, conf=0.5).detect(big)
    assert box_iou_np(d2.boxes[d2.class_names == "person"] / 2, gt).max(0).min() > 0.8


def test_the_loss_agrees_with_the_pretrained_network(coco_model):
    """The fine-tuning loss on a photo the source detects well (FudanPed00001's two annotated pedestrians): SimOTA
    assigns anchors to both, their boxes overlap the annotation (the loss decodes anchors as the network does),
    and the gradient reaches the attention gates of a model that starts as the source."""
    from vslam.nn.detectors.yolox_loss import freeze_bn, yolox_loss

    im = frame("fudan")
    x = as_input(im)
    r = min(416 / im.shape[1], 416 / im.shape[0])
    gt = torch.tensor([[160, 182, 302, 431], [420, 171, 535, 486]], dtype=torch.float32) * r
    targets = [(gt, torch.tensor([0, 0]))]
    with torch.no_grad():
        out = coco_model({"image": x})
    loss = yolox_loss(out, targets, (416, 416))
    # measured 17 positives, mean 1 - IoU^2 0.24 (IoU ~0.87); anchors or targets in another frame than the
    # network's boxes (x and y swapped, targets not scaled by the letterbox) give few positives or low IoUs
    assert int(loss["fg"]) >= 4 and float(loss["box"]) < 0.5
    model = freeze_bn(DETECTORS.pretrained("yolox-nano", {"attention": "se"}).train())
    yolox_loss(model({"image": x}), targets, (416, 416))["loss"].backward()
    assert all(float(p.grad.abs().max()) > 0 for n, p in model.named_parameters() if n.endswith(".gate"))
