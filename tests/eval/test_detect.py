"""``vslam detect``: COCO results entries (bbox as x, y, w, h; COCO category ids; RLE masks) from a detector."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.cli import main
from vslam.dynamic.detector import Detections
from vslam.errors import ConfigError
from vslam.eval.detect import coco_results, image_files, rle
from vslam.paths import data_root


class Fixed:
    """A detector that returns the same two detections (a person with a mask, a car) on every image."""

    names = ["person", "car"]

    def __init__(self, shape: tuple[int, int]):
        m = np.zeros((2, *shape), bool)
        m[0, 2:5, 1:3] = True
        self.det = Detections(np.array([[1.0, 2.0, 3.0, 5.0], [10.0, 0.0, 30.0, 8.0]]), np.array([0.9, 0.2]),
                              np.array([0, 1]), np.array(["person", "car"], dtype=object), m, 4.0)

    def detect(self, image):
        return self.det


def test_results_entries_are_coco_format(tmp_path):
    files = []
    for stem in ("000000000042", "frame_a"):
        cv2.imwrite(str(tmp_path / f"{stem}.png"), np.zeros((8, 32, 3), np.uint8))
        files.append(tmp_path / f"{stem}.png")
    res = coco_results(Fixed((8, 32)), files, threshold=0.5)
    assert len(res) == 2  # the car scores 0.2 < 0.5
    a, b = res
    assert a["image_id"] == 42 and b["image_id"] == 1  # a numeric stem is the id, else the position
    assert a["category_id"] == 1 and a["category_name"] == "person"
    assert a["bbox"] == [1.0, 2.0, 2.0, 3.0] and a["score"] == 0.9
    assert a["segmentation"]["size"] == [8, 32]
    res = coco_results(Fixed((8, 32)), files[:1], threshold=0.1)
    assert [r["category_id"] for r in res] == [1, 3]  # COCO's ids: person 1, car 3


def test_rle_is_coco_uncompressed_rle():
    rng = np.random.default_rng(0)
    m = rng.random((7, 11)) > 0.6
    m[0, 0] = True  # a mask that starts with a set pixel: counts begin with a zero run
    r = rle(m)
    assert r["counts"][0] == 0 and sum(r["counts"]) == m.size
    flat = np.concatenate([np.full(c, i % 2, bool) for i, c in enumerate(r["counts"])])
    assert np.array_equal(flat.reshape(m.shape, order="F"), m)
    mask_api = pytest.importorskip("pycocotools.mask")
    decoded = mask_api.decode(mask_api.frPyObjects(r, *r["size"]))
    assert np.array_equal(decoded.astype(bool), m)


def test_missing_image_is_one_line_error(tmp_path):
    with pytest.raises(ConfigError, match="nope.png: no such image"):
        image_files([tmp_path / "nope.png"])


def test_cli_on_a_real_photo(tmp_path):
    """The shipped YOLOX model through the command: the two pedestrians of FudanPed00001 as COCO person boxes."""
    photo = data_root() / "penn_fudan/PennFudanPed/JPEGImages/FudanPed00001.jpg"
    model = Path(__file__).resolve().parents[2] / "vslam" / "models" / "yolox_nano_slam.pt"
    if not photo.is_file() or not model.is_file():
        pytest.skip(f"needs {photo} (set VSLAM_DATA) and the shipped {model.name}")
    out = tmp_path / "dets.json"
    assert main(["-q", "detect", str(photo), "-o", str(out), "--threshold", "0.5"]) == 0  # the default: YOLOX
    res = json.loads(out.read_text())
    people = [r for r in res if r["category_id"] == 1]
    assert len(people) == 2 and all(r["image_id"] == 0 and r["file_name"] == str(photo) for r in people)
    x, y, w, h = sorted(r["bbox"] for r in people)[0]
    gt = (160, 182, 302 - 160, 431 - 182)  # PennFudanPed/Annotation/FudanPed00001.txt, the left pedestrian
    assert abs(x - gt[0]) < 15 and abs(y - gt[1]) < 15 and abs(w - gt[2]) < 25 and abs(h - gt[3]) < 25
    cocopy = pytest.importorskip("pycocotools.coco")
    api = cocopy.COCO()
    api.dataset = {"images": [{"id": 0, "height": 536, "width": 559}], "categories": [{"id": 1, "name": "person"},
                   {"id": 3, "name": "car"}], "annotations": []}
    api.createIndex()
    assert len(api.loadRes(str(out)).anns) == len(res)  # pycocotools reads it as results
