"""The attention ablation: every weights file on the same held-out sets, one recipe enforced; float16 weights
load back to the float32 model's outputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import vslam.train.detector as tr  # noqa: E402
from vslam.dynamic.detector import load_model, save_checkpoint  # noqa: E402
from vslam.dynamic.model import DetectorConfig, YoloDetector  # noqa: E402
from vslam.errors import ConfigError  # noqa: E402
from vslam.eval.ablation import evaluate_detectors, format_table  # noqa: E402

torch.set_num_threads(1)
TOY = dict(toy=True, synthetic_frames=8, synthetic_stride=2, threads=1)


def test_float16_weights_are_half_the_size_and_give_the_same_boxes(tmp_path):
    torch.manual_seed(0)
    m = YoloDetector(DetectorConfig(attention="esea", num_classes=2, width=0.125)).eval()
    full = save_checkpoint(tmp_path / "f32.pt", m, ["person", "car"])
    half = save_checkpoint(tmp_path / "f16.pt", m, ["person", "car"], half=True)
    assert half.stat().st_size < 0.6 * full.stat().st_size
    back, _ = load_model(half)
    assert all(p.dtype == torch.float32 for p in back.parameters())
    x = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        a, b = m(x), back.eval()(x)
    for u, v in zip(a, b):
        torch.testing.assert_close(u, v, rtol=0, atol=2e-2)


def test_ablation_compares_variants_of_one_recipe_and_refuses_others(tmp_path):
    files = []
    for att in ("none", "esea"):
        cfg = tr.TrainConfig(out=str(tmp_path / att), attention=att, weights=str(tmp_path / f"{att}.pt"), **TOY)
        tr.train(cfg)
        files.append(str(tmp_path / f"{att}.pt"))
    res = evaluate_detectors(files, threads=1)
    assert list(res["models"]) == ["none.pt", "esea.pt"] and res["sets"] == {"synthetic-val": 6}  # the toy recipe: 24 frames, every 4th
    for name, m in res["models"].items():
        assert 0.0 <= m["sets"]["synthetic-val"]["AP50/person"] <= 1.0 and m["ms_640x480"] > 0
    assert res["models"]["esea.pt"]["params"] > res["models"]["none.pt"]["params"]  # the attention blocks
    # the numbers are those of the trainer's own held-out evaluation, re-measured from the float16 copy
    own = torch.load(tmp_path / "esea" / "model.pt", weights_only=False)["metrics"]["synthetic-val"]["AP50/person"]
    assert res["models"]["esea.pt"]["sets"]["synthetic-val"]["AP50/person"] == pytest.approx(own, abs=0.05)
    table = format_table(res)
    assert table[0].startswith("| weights | attention |") and len(table) == 4
    other = tr.TrainConfig(out=str(tmp_path / "lr"), lr=1e-3, weights=str(tmp_path / "lr.pt"), **TOY)
    tr.train(other)
    with pytest.raises(ConfigError, match="another recipe.*lr"):
        evaluate_detectors([files[0], str(tmp_path / "lr.pt")], threads=1)
