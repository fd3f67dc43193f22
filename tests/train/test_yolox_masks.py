"""The mask-head trainer (vslam.train.yolox_masks) in its toy mode: the loss falls, only the mask head
learns, and an interrupted run resumed from last.pt ends with the weights of an uninterrupted one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vslam.errors import ConfigError
from vslam.nn.checkpoint import load_model, read_checkpoint
from vslam.nn.registry import DETECTORS
from vslam.train.yolox_masks import MaskTrainConfig, mask_loss, train


class Stop(Exception):
    pass


def _losses(path) -> np.ndarray:
    rows = [r.split(",") for r in path.read_text().splitlines()[1:]]
    return np.array([float(r[2]) for r in rows if r[2] != "nan"])


def test_toy_run_lowers_the_loss_and_trains_only_the_head(tmp_path):
    torch.set_num_threads(1)
    train(MaskTrainConfig(out=str(tmp_path), toy=True, iterations=60, log_every=1))
    loss = _losses(tmp_path / "log.csv")
    assert loss[-10:].mean() < loss[:10].mean() - 0.1
    model, ck = load_model(tmp_path / "model.pt", DETECTORS)
    assert ck["arch"] == "yolox-nano-masks" and ck["conf"]["mask"]["side"] == 28
    torch.manual_seed(0)  # the toy network's start: its box part never moved
    start = DETECTORS.build("yolox-nano-masks", ck["conf"]).state_dict()
    for k, v in model.state_dict().items():
        assert torch.equal(v, start[k]) != k.startswith("mask_head."), k


def test_resume_gives_the_uninterrupted_weights(tmp_path):
    torch.set_num_threads(1)
    cfg = MaskTrainConfig(out=str(tmp_path / "a"), toy=True, iterations=20)
    train(cfg)

    def stop_at_10(done: int, total: int) -> None:
        if done == 10:
            raise Stop

    b = MaskTrainConfig(out=str(tmp_path / "b"), toy=True, iterations=20)
    with pytest.raises(Stop):
        train(b, progress=stop_at_10)
    assert read_checkpoint(tmp_path / "b" / "last.pt", "x")["iteration"] == 10
    train(MaskTrainConfig(out=str(tmp_path / "b"), toy=True, iterations=20, resume=True))
    wa = read_checkpoint(tmp_path / "a" / "model.pt", "x")["state_dict"]
    wb = read_checkpoint(tmp_path / "b" / "model.pt", "x")["state_dict"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    with pytest.raises(ConfigError, match="different config"):
        train(MaskTrainConfig(out=str(tmp_path / "b"), toy=True, iterations=20, resume=True, jitter=0.2))


def test_mask_loss_is_low_for_the_right_mask():
    t = torch.zeros(2, 8, 8)
    t[:, 2:6, 2:6] = 1.0
    good, bad = mask_loss((t * 2 - 1) * 10, t, 1.0), mask_loss((1 - t * 2) * 10, t, 1.0)
    assert float(good) < 0.01 and float(bad) > 5.0


def test_config_errors():
    with pytest.raises(ConfigError, match="multiple of 32"):
        MaskTrainConfig(img_size=100)
