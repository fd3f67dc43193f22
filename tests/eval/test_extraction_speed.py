"""The extraction speed bench (``eval.extraction_speed``, bench kind ``extraction``): every method timed on
every frame, ratios to ORB, ALIKE's steps and layers, the guided matcher; and the OpenMP wait policy set before
torch loads (``vslam/__init__.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from vslam.data.types import PinholeCamera  # noqa: E402
from vslam.eval.extraction_speed import LAYERS, SpeedSet, extraction_speed, format_table  # noqa: E402
from vslam.features import FeatureConfig  # noqa: E402


def _frames(n: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    big = cv2.GaussianBlur(rng.standard_normal((300, 400)).astype(np.float32), (0, 0), 2.0)
    big = ((big - big.min()) / (big.max() - big.min()) * 255).astype(np.uint8)
    return [big[2 * i:2 * i + 240, 3 * i:3 * i + 320].copy() for i in range(n)]  # a slow pan


def test_times_every_method_and_step():
    cam = PinholeCamera(fx=300.0, fy=300.0, cx=160, cy=120, width=320, height=240)
    cfg = FeatureConfig(extractor="alike-t", n_features=300, input_scale=0.5, min_score=0.0)
    res = extraction_speed([SpeedSet("toy", _frames(), cam, cfg)], repeats=1, threads=1, runtimes=("torch",))
    r = res["toy"]
    assert set(r["ms"]) == {"orb", "alike-t torch"} and r["ratio"]["orb"] == 1.0
    assert set(r["steps"]["alike-t torch"]) == {"prep", "network", "nms", "select", "refine", "describe"}
    assert set(r["layers"]) == set(LAYERS) and all(v > 0 for v in r["layers"].values())
    assert 0 < r["keypoints"]["alike-t torch"] <= 300
    # a slow pan: most keypoints of one frame are found near the same pixels in the next
    assert r["matches"]["float"] > 50 and set(r["match_ms"]) == {"float", "binary"}
    assert r["size"] == "320x240" and res["threads"] == 1
    table = format_table(res)
    assert "| toy | 320x240 @ 0.5 | 300 |" in table[2]


def test_extra_stages_and_front_end():
    """A further stage is timed per frame with the frame's ALIKE keypoints; front_end = ALIKE + the stages."""
    cam = PinholeCamera(fx=300.0, fy=300.0, cx=160, cy=120, width=320, height=240)
    cfg = FeatureConfig(extractor="alike-t", n_features=200, input_scale=0.5, min_score=0.0)
    seen = []
    stage = ("masks", lambda im, xy: (seen.append(len(xy)), time.sleep(0.002)))
    r = extraction_speed([SpeedSet("toy", _frames(2), cam, cfg, (stage,))], repeats=1, threads=1,
                         runtimes=("torch",))["toy"]
    assert len(seen) == 2 + 2 and all(0 < n <= 200 for n in seen)  # warm-up frames, then the timed ones
    assert r["ms"]["masks"] >= 2.0 and r["ms"]["front_end"] >= r["ms"]["masks"] + 0.5 * r["ms"]["alike-t torch"]
    other = {**r, "ms": {k: v for k, v in r["ms"].items() if k not in ("masks", "front_end")}}
    table = format_table({"a": r, "b": other})  # a stage only one set times: a dash in the other's row
    assert "masks ms" in table[0] and table[3].count("–") == 2


def test_openmp_waits_passively():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", "import vslam, os; print(os.environ['OMP_WAIT_POLICY'])"],
                         env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
