"""Teacher pseudo-labels (issue 40): unlabelled teacher boxes become boxes without masks, labelled objects and
ignore regions are left alone, and a rerun reads the cache instead of running the teacher."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
import pytest

from vslam.errors import ConfigError
from vslam.paths import data_root
from vslam.train.detector_data import Sample, mask_validity
from vslam.train.pseudo import FastestDetTeacher, PseudoConfig, pseudo_label, pseudo_label_sources, pseudo_report

PENN = data_root() / "penn_fudan" / "PennFudanPed"
TEACHER = data_root() / "teachers" / "fastestdet" / "FastestDet.onnx"
CLASSES = ("person", "bicycle", "car", "chair")


@dataclass
class _Det:
    boxes: np.ndarray
    scores: np.ndarray
    class_names: np.ndarray


class FakeTeacher:
    """Always the same detections; counts its runs."""

    def __init__(self, fingerprint: str = "fake-1"):
        self.fingerprint, self.calls = fingerprint, 0

    def detect(self, image: np.ndarray) -> _Det:
        self.calls += 1
        boxes = np.array([[10.0, 10, 40, 90],  # on the labelled person: the same object
                          [100, 20, 130, 100],  # a person nobody labelled
                          [150, 60, 195, 95],  # a truck: the list's car
                          [60, 5, 90, 30],  # a person below the threshold
                          [12, 12, 38, 50],  # the upper half of the labelled person (IoU < 0.5, inside it)
                          [140, 100, 180, 118],  # a car inside the ignore region
                          [0, 0, 60, 10]], np.float64)  # a chair: not a kept class
        return _Det(boxes, np.array([0.9, 0.8, 0.7, 0.3, 0.9, 0.9, 0.9]),
                    np.array(["person", "person", "truck", "person", "person", "car", "chair"]))


def _samples() -> list[Sample]:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (120, 200, 3), dtype=np.uint8)
    masks = np.zeros((1, 120, 200), bool)
    masks[0, 10:90, 10:40] = True
    a = Sample(img, np.array([[10.0, 10, 40, 90]]), np.array([0]), masks, None, np.array([[130.0, 95, 200, 120]]))
    b = Sample(img[:, ::-1].copy(), np.zeros((0, 4)), np.zeros(0, np.int64))
    return [a, b]


def test_teacher_boxes_are_added_where_no_label_is_and_cached(tmp_path):
    cfg = PseudoConfig(cache=str(tmp_path / "cache"))
    teacher = FakeTeacher()
    out, stats = pseudo_label(_samples(), CLASSES, cfg, teacher, "fake")
    assert teacher.calls == 2 and stats.teacher_runs == 2 and stats.cache_hits == 0
    a, b = out
    np.testing.assert_array_equal(a.boxes, [[10, 10, 40, 90], [100, 20, 130, 100], [150, 60, 195, 95]])
    assert a.labels.tolist() == [0, 0, 2] and mask_validity(a).tolist() == [True, False, False]
    assert a.masks.shape == (3, 120, 200) and not a.masks[1:].any() and a.masks[0].sum() == 80 * 30
    assert len(b.boxes) == 5 and not mask_validity(b).any() and b.masks is None  # no labels: all but the chair
    assert stats.added == {"person": 4, "car": 3} and stats.overlapping == 2 and stats.in_ignore == 1
    assert "fake" in pseudo_report({"fake": stats})

    again, stats2 = pseudo_label(_samples(), CLASSES, cfg, teacher, "fake")
    assert teacher.calls == 2 and stats2.cache_hits == 2 and stats2.teacher_runs == 0  # no teacher run
    for x, y in zip(out, again):
        np.testing.assert_array_equal(x.boxes, y.boxes)
        np.testing.assert_array_equal(x.labels, y.labels)
    # another teacher, or another threshold, is another key
    pseudo_label(_samples(), CLASSES, cfg, FakeTeacher("fake-2"), "fake")
    other = FakeTeacher()
    pseudo_label(_samples(), CLASSES, PseudoConfig(cache=str(tmp_path / "cache"), threshold=0.6), other, "fake")
    assert other.calls == 2


def test_cover_rule_off_keeps_the_half_person_and_a_teacher_needs_a_fingerprint(tmp_path):
    cfg = PseudoConfig(cache=str(tmp_path / "c"), max_cover=1.0)
    out, stats = pseudo_label(_samples()[:1], CLASSES, cfg, FakeTeacher(), "fake")
    assert len(out[0].boxes) == 4 and stats.overlapping == 1
    with pytest.raises(ConfigError, match="fingerprint"):
        pseudo_label(_samples(), CLASSES, cfg, FakeTeacher(""), "fake")
    with pytest.raises(ConfigError, match="pseudo.threshold"):
        PseudoConfig(threshold=0.0)


def test_a_missing_onnxruntime_is_a_one_line_error(tmp_path, monkeypatch):
    if not TEACHER.is_file():
        pytest.skip("teachers/fastestdet not in $VSLAM_DATA")
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as if not installed
    with pytest.raises(ConfigError, match=r"pip install 'vslam\[teacher\]'"):
        pseudo_label(_samples(), CLASSES, PseudoConfig(cache=str(tmp_path / "c")), None, "x")
    with pytest.raises(ConfigError, match="not found"):
        FastestDetTeacher(tmp_path / "none.onnx")


def test_fastestdet_pseudo_labels_on_penn_fudan_are_cached(tmp_path):
    pytest.importorskip("onnxruntime", reason="the teacher extra (vslam[teacher]) is not installed")
    if not (TEACHER.is_file() and PENN.is_dir()):
        pytest.skip("teachers/fastestdet or penn_fudan/PennFudanPed not in $VSLAM_DATA")
    from vslam.train.photos import penn_fudan_samples

    samples = penn_fudan_samples(PENN, CLASSES)[:4]
    cfg = PseudoConfig(cache=str(tmp_path / "cache"), threads=1)
    out, stats = pseudo_label_sources({"penn": samples}, CLASSES, cfg)
    assert stats["penn"].teacher_runs == 4 and stats["penn"].images == 4
    again, stats2 = pseudo_label_sources({"penn": samples}, CLASSES, cfg)
    assert stats2["penn"].cache_hits == 4 and stats2["penn"].teacher_runs == 0
    for x, y, s in zip(out["penn"], again["penn"], samples):
        np.testing.assert_array_equal(x.boxes, y.boxes)
        np.testing.assert_array_equal(x.boxes[:len(s.boxes)], s.boxes)  # the labels come first, unchanged
        assert mask_validity(x)[:len(s.boxes)].all() and not mask_validity(x)[len(s.boxes):].any()
