"""Training recipe: a toy CPU run end to end, resumable to the same weights, and the augmentation keeps boxes on
their objects."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import vslam.train.detector as tr  # noqa: E402
from vslam.eval.detection_metrics import average_precision  # noqa: E402
from vslam.train.detector_data import Sample, collate, place  # noqa: E402

torch.set_num_threads(1)
CFG = dict(toy=True, synthetic_frames=8, synthetic_stride=2, threads=1)


def test_place_moves_boxes_with_the_object():
    img = np.full((120, 160, 3), 40, np.uint8)
    img[30:90, 50:80] = 255  # the object: a white block at x 50..79, y 30..89
    s = Sample(img, np.array([[50.0, 30.0, 80.0, 90.0]]), np.array([0]))
    for seed in range(20):
        p = place(s, 96, np.random.default_rng(seed))
        if len(p.boxes) == 0:
            continue
        x1, y1, x2, y2 = np.round(p.boxes[0]).astype(int)
        inside = p.image[y1 + 2:y2 - 2, x1 + 2:x2 - 2].astype(float).mean()
        assert inside > 150, seed  # the box still frames the (jittered) white block
    e = place(s, 96, None)  # letterbox: scale 0.6, vertical padding 12
    np.testing.assert_allclose(e.boxes, [[30.0, 30.0, 48.0, 66.0]])
    imgs, boxes, labels, mask = collate([e, Sample(e.image, np.zeros((0, 4)), np.zeros(0, np.int64))])
    assert imgs.shape == (2, 3, 96, 96) and boxes.shape == (2, 1, 4) and mask.tolist() == [[True], [False]]


def test_average_precision():
    gts = [(np.array([[0.0, 0, 10, 10], [20, 20, 30, 30]]), np.array([0, 0]))]
    perfect = [(np.array([[0.0, 0, 10, 10], [20, 20, 30, 30]]), np.array([0.9, 0.8]), np.array([0, 0]))]
    assert average_precision(perfect, gts, 0, 0.5) == pytest.approx(1.0)
    half = [(np.array([[0.0, 0, 10, 10], [50, 50, 60, 60]]), np.array([0.9, 0.8]), np.array([0, 0]))]
    assert average_precision(half, gts, 0, 0.5) == pytest.approx(51 / 101)  # recall 0.5 at precision 1
    assert np.isnan(average_precision(perfect, gts, 1, 0.5))


def test_toy_run_is_resumable_to_the_same_weights(tmp_path, monkeypatch):
    full = tr.TrainConfig(out=str(tmp_path / "a"), **CFG)
    metrics = tr.train(full)
    assert "AP50/person" in metrics["synthetic-val"]
    log = np.genfromtxt(tmp_path / "a" / "log.csv", delimiter=",", names=True)
    assert np.all(np.isfinite(log["loss"]))

    # the same run interrupted after the checkpoint at iteration 10, then resumed
    cut = dataclasses.replace(full, out=str(tmp_path / "b"))
    real_lr = tr._lr

    def interrupt(cfg, it):
        if it == 10:
            raise KeyboardInterrupt
        return real_lr(cfg, it)

    monkeypatch.setattr(tr, "_lr", interrupt)
    with pytest.raises(KeyboardInterrupt):
        tr.train(cut)
    monkeypatch.setattr(tr, "_lr", real_lr)
    tr.train(dataclasses.replace(cut, resume=True))
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=False)["model"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)


def test_init_starts_from_a_checkpoint(tmp_path):
    """``init``: a further round starts from the given weights (with a vanishing learning rate it ends where
    the first round did); a checkpoint of another architecture is refused."""
    first = tr.TrainConfig(out=str(tmp_path / "a"), **CFG)
    tr.train(first)
    again = dataclasses.replace(first, out=str(tmp_path / "b"), lr=1e-12, init=str(tmp_path / "a" / "model.pt"))
    tr.train(again)
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=False)["model"]
    for k in a:
        if a[k].is_floating_point() and "running" not in k:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)
    with pytest.raises(tr.ConfigError, match="another architecture"):
        tr.train(dataclasses.replace(again, out=str(tmp_path / "c"), attention="cbam"))


def test_batch_workers_give_the_weights_of_the_training_loop(tmp_path):
    """``workers``: batches drawn by spawned processes (each rebuilding the training data) are the batches the
    loop would draw itself, so the weights are the same bit for bit; resuming with workers works too."""
    base = dict(CFG, iterations=6, bn_batches=1, synthetic_val_seeds=())
    tr.train(tr.TrainConfig(out=str(tmp_path / "a"), **base))
    tr.train(tr.TrainConfig(out=str(tmp_path / "b"), workers=2, **base))
    a = torch.load(tmp_path / "a" / "model.pt", weights_only=False)["model"]
    b = torch.load(tmp_path / "b" / "model.pt", weights_only=False)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_batches_ahead_keep_order_and_bound():
    """The prefetch returns the pool's results in iteration order and never has more than n in flight."""

    class Pool:
        def __init__(self):
            self.in_flight = self.most = 0

        def apply_async(self, fn, args):
            self.in_flight += 1
            self.most = max(self.most, self.in_flight)
            pool = self

            class Result:
                def get(self):
                    pool.in_flight -= 1
                    return args[0]

            return Result()

    pool = Pool()
    assert list(tr._ahead(pool, range(3, 20), 4)) == list(range(3, 20))
    assert pool.most == 4


def test_no_evaluation_when_asked(tmp_path):
    metrics = tr.train(tr.TrainConfig(out=str(tmp_path / "a"), **dict(CFG, iterations=2, bn_batches=1), evaluate=False))
    assert metrics == {} and (tmp_path / "a" / "model.pt").is_file()


def test_hsv_jitter_table_equals_the_per_pixel_formula():
    """The lookup-table HSV jitter gives the bytes of the per-pixel float formula it replaced (the recipe's
    samples, hence trained weights, are unchanged)."""
    import cv2

    from vslam.train.detector_data import _hsv_jitter

    def per_pixel(img, rng, h=0.015, s=0.7, v=0.4):
        gains = rng.uniform(-1, 1, 3) * (h, s, v) + 1
        hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV).astype(np.float32)
        hsv[..., 0] = (hsv[..., 0] * gains[0]) % 180
        hsv[..., 1:] = np.clip(hsv[..., 1:] * gains[1:], 0, 255)
        return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)

    for seed in range(50):
        img = np.random.default_rng(seed).integers(0, 256, (48, 64, 3), dtype=np.uint8)
        np.testing.assert_array_equal(_hsv_jitter(img, np.random.default_rng([seed, 1])),
                                      per_pixel(img, np.random.default_rng([seed, 1])), err_msg=str(seed))


def test_the_new_sources_are_checked_by_name():
    from vslam.errors import ConfigError
    from vslam.train.detector import TrainConfig, training_data

    with pytest.raises(ConfigError, match="unknown source"):
        TrainConfig(cutouts=("flickr",))
    with pytest.raises(ConfigError, match="unknown source"):
        TrainConfig(pseudo=("tum",))
    with pytest.raises(ConfigError, match="train.pseudo names \\['kitti_object'\\]"):
        training_data(TrainConfig(coco="", synthetic_seeds=(), pseudo=("kitti_object",)))
