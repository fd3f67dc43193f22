"""YOLOX fine-tuning (``vslam.train.yolox``, ``yolox_data``): placement keeps boxes on their objects,
a toy run lowers the loss and resumes to the weights of an uninterrupted run, and its checkpoint loads as SLAM's
detector. Synthetic samples only: no data folder needed, seconds on 2 threads."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from vslam.dynamic.yolox_detector import letterbox_top_left
from vslam.train import yolox as yt
from vslam.train.detector_data import Sample
from vslam.train.yolox_data import YoloxData, YoloxDataConfig, draw_batch, place_rect

ROOT = Path(__file__).resolve().parents[2]


def _red_box_image(w: int, h: int, box: tuple[int, int, int, int]) -> Sample:
    """Grey image with a saturated red rectangle at ``box`` (x1, y1, x2, y2; x2 / y2 exclusive) labelled 0."""
    img = np.full((h, w, 3), 90, np.uint8)
    x1, y1, x2, y2 = box
    img[y1:y2, x1:x2] = (0, 0, 255)
    return Sample(img, np.array([box], np.float64), np.array([0]), ignore=np.array([[0.0, 0.0, 10.0, h / 2]]))


def _saturated_bbox(img: np.ndarray) -> np.ndarray:
    """Box of the pixels that are clearly coloured (grey background and padding have no saturation)."""
    sat = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)[..., 1]
    ys, xs = np.nonzero(sat > 60)
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)


def test_letterbox_placement_is_the_inference_letterbox():
    s = _red_box_image(200, 100, (40, 20, 80, 70))
    out = place_rect(s, (128, 128), (128, 128), None)
    ref, r = letterbox_top_left(s.image, (128, 128))
    np.testing.assert_array_equal(out.image, ref)
    assert r == pytest.approx(0.64)
    np.testing.assert_allclose(out.boxes[0], np.array([40, 20, 80, 70]) * 0.64)
    np.testing.assert_allclose(_saturated_bbox(out.image), out.boxes[0], atol=1.0)
    np.testing.assert_allclose(out.ignore[0], np.array([0, 0, 10, 50]) * 0.64)


@pytest.mark.parametrize("seed", range(8))
def test_jittered_placement_keeps_the_box_on_its_object(seed):
    """Random scale, window, flip and HSV jitter: the label box is where the red pixels landed (to the blur of
    resizing), and the ignore region moved by the same map."""
    s = _red_box_image(160, 120, (60, 30, 100, 90))
    rng = np.random.default_rng(seed)
    out = place_rect(s, (96, 96), (128, 128), rng, scale=(0.8, 1.2), min_visible=0.99)
    if not len(out.boxes):  # cut by the window: then no red pixel may be left whole
        return
    np.testing.assert_allclose(_saturated_bbox(out.image), out.boxes[0], atol=1.5)
    assert out.labels.tolist() == [0]
    left_edge = out.ignore is not None and (out.ignore[:, 0].min() < 1 or out.ignore[:, 2].max() > 95)
    assert out.ignore is None or left_edge  # the region at the image's left edge stays at an edge (flip: the right)


def _toy_data() -> YoloxData:
    rng = np.random.default_rng(5)
    square = []
    for k in range(3):
        img = rng.integers(0, 255, (96, 128, 3), dtype=np.uint8)
        x, y = 20 + 15 * k, 10 + 5 * k
        img[y:y + 60, x:x + 25] = (40, 160, 230)
        square.append(Sample(img, np.array([[x, y, x + 25, y + 60]], np.float64), np.array([0])))
    img = rng.integers(0, 255, (64, 192, 3), dtype=np.uint8)
    img[10:50, 100:150] = (200, 30, 30)
    wide = [Sample(img, np.array([[100.0, 10, 150, 50]]), np.array([2]), ignore=np.array([[0.0, 0, 20, 64]]))]
    return YoloxData({"coco": square}, wide, [], [])


def _cfg(tmp_path: Path, name: str, **kw) -> yt.YoloxTrainConfig:
    base = dict(out=str(tmp_path / name), lr=1e-3, ema_decay=0.5, ema_tau=1.0, threads=1, batch=2, warmup=2,
                log_every=1, pseudo=False, data=YoloxDataConfig(**yt.TOY_DATA))
    return yt.YoloxTrainConfig(**(base | kw))


def _state(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=True)["state_dict"]


def test_toy_run_lowers_the_loss_resumes_exactly_and_loads_as_the_detector(tmp_path, monkeypatch):
    data = _toy_data()
    cfg = _cfg(tmp_path, "a", iterations=8, ckpt_every=3)
    yt.train(cfg, data=data)
    # the loss on fixed batches (square and wide) falls from the start's
    start, _ = yt.load_start(cfg)
    trained, _ = yt.load_start(dataclasses.replace(cfg, init=str(tmp_path / "a" / "model.pt")))
    dc = cfg.data
    batches = [draw_batch(data, dc, 99, it, 2, 0) for it in (0, 2)]
    assert [b.wide for b in batches] == [False, True]
    for b in batches:
        with torch.no_grad():
            before = float(yt.batch_loss(start.eval(), b, torch.device("cpu"))["loss"])
            after = float(yt.batch_loss(trained.eval(), b, torch.device("cpu"))["loss"])
        assert after < 0.9 * before, (b.wide, before, after)

    # the same run interrupted after the checkpoint at iteration 6, then resumed: the same weights
    cut = dataclasses.replace(cfg, out=str(tmp_path / "b"))
    real_lr = yt._lr

    def interrupt(c, it):
        if it == 6:
            raise KeyboardInterrupt
        return real_lr(c, it)

    monkeypatch.setattr(yt, "_lr", interrupt)
    with pytest.raises(KeyboardInterrupt):
        yt.train(cut, data=data)
    monkeypatch.setattr(yt, "_lr", real_lr)
    yt.train(dataclasses.replace(cut, resume=True), data=data)
    a, b = _state(tmp_path / "a" / "model.pt"), _state(tmp_path / "b" / "model.pt")
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)
    with pytest.raises(yt.ConfigError, match="different config"):
        yt.train(dataclasses.replace(cut, resume=True, lr=2e-3), data=data)

    # the result is SLAM's detector checkpoint: it loads through load_detector as a YoloxDetector
    from vslam.dynamic.detector import load_detector
    from vslam.dynamic.yolox_detector import YoloxDetector

    det = load_detector(tmp_path / "a" / "model.pt", conf=0.01)
    assert isinstance(det, YoloxDetector)
    assert det.names == ["person", "bicycle", "car", "motorcycle", "bus", "truck"]
    out = det.detect(data.sources["coco"][0].image)
    assert out.boxes.shape[1] == 4 and len(out.boxes) == len(out.scores)
    loaded = {k: v for k, v in trained.state_dict().items()}
    for k, v in a.items():
        torch.testing.assert_close(loaded[k], v, rtol=0, atol=0, msg=k)


def test_config_file_loads():
    from vslam.config import load_config

    cfg = load_config(yt.YoloxTrainConfig, ROOT / "configs" / "train_yolox.yaml")
    assert isinstance(cfg.data, YoloxDataConfig)
    assert cfg.data.wide_fit == (1248, 384) and cfg.threads <= 2
    with pytest.raises(yt.ConfigError, match="multiples of 32"):
        YoloxDataConfig(canvas=(100, 96))


def test_train_only_keeps_every_other_tensor_and_names_a_wrong_prefix(tmp_path):
    data = _toy_data()
    heads = ("head.cls_convs", "head.cls_preds", "head.obj_preds")
    cfg = _cfg(tmp_path, "c", iterations=3, ckpt_every=10, train_only=heads)
    yt.train(cfg, data=data)
    start = yt.load_start(cfg)[0].state_dict()
    trained = _state(tmp_path / "c" / "model.pt")
    # (the EMA's d * w + (1 - d) * w rounds a frozen tensor by an ulp or so)
    moved = {k for k, v in start.items() if v.is_floating_point() and (v - trained[k]).abs().max() > 1e-5}
    assert moved and all(k.startswith(heads) for k in moved), sorted(moved)[:5]
    assert any(k.startswith("head.cls_preds") for k in moved)
    assert not any(k.startswith(("head.reg_", "head.stems", "neck.")) for k in moved)  # the boxes stay the source's
    with pytest.raises(yt.ConfigError, match="head.cls_pred "):
        yt.train(_cfg(tmp_path, "d", iterations=1, train_only=("head.cls_pred ",)), data=data)


def test_box_distill_loss_is_one_minus_iou_where_the_teacher_sees_something():
    boxes = torch.tensor([[[0.0, 0, 10, 10], [20, 20, 30, 30], [0, 0, 4, 4]]])
    logits = torch.full((1, 3, 5 + 6), -9.0)
    logits[0, :2, 4], logits[0, :2, 5] = 3.0, 3.0  # the teacher scores anchors 0 and 1 (~0.9), not 2
    ref = {"boxes": boxes, "logits": logits}
    assert float(yt.box_distill_loss({"boxes": boxes.clone(), "logits": logits}, ref)) == 0.0
    moved = boxes.clone().requires_grad_(True)
    shifted = moved + torch.tensor([[[5.0, 0, 5, 0], [0, 0, 0, 0], [50, 50, 50, 50]]])  # anchor 2 is not scored
    loss = yt.box_distill_loss({"boxes": shifted, "logits": logits}, ref)
    assert loss.item() == pytest.approx((1 - 50 / 150) / 2)  # IoU of [5,0,15,10] with [0,0,10,10]: 50 / 150
    loss.backward()
    assert moved.grad[0, 2].abs().sum() == 0 and moved.grad[0, 0].abs().sum() > 0
    none = {"boxes": boxes, "logits": torch.full((1, 3, 11), -9.0)}
    assert yt.box_distill_loss({"boxes": moved, "logits": logits}, none).item() == 0.0


def test_box_distill_run_keeps_the_boxes_nearer_the_start(tmp_path):
    data = _toy_data()
    yt.train(_cfg(tmp_path, "free", iterations=6), data=data)
    yt.train(_cfg(tmp_path, "kept", iterations=6, box_distill=20.0, box_distill_min_score=0.0), data=data)
    cfg = _cfg(tmp_path, "x")
    start = yt.load_start(cfg)[0].eval()
    b = draw_batch(data, cfg.data, 7, 0, 2, 0)
    x = {"image": torch.from_numpy(b.images).float()}
    with torch.no_grad():
        ref = start(x)
        gaps = {}
        for name in ("free", "kept"):
            net = yt.load_start(dataclasses.replace(cfg, init=str(tmp_path / name / "model.pt")))[0].eval()
            gaps[name] = float(yt.box_distill_loss(net(x), ref, min_score=0.0))
    assert gaps["kept"] < 0.7 * gaps["free"], gaps
