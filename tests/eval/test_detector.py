"""``vslam eval-detector`` (issue 40): AP against pycocotools, recall / precision / mask IoU on constructed cases,
FastestDet's decoding, and the command end to end on a 5-image Penn-Fudan subset."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.cli import main
from vslam.eval.detection_metrics import IOU_THRESHOLDS, average_precision, match
from vslam.eval.detector import Prediction, evaluate, format_report
from vslam.paths import data_root
from vslam.train.photos import Record
from vslam.train.teacher import decode

PENN = data_root() / "penn_fudan" / "PennFudanPed"


def _random_case(rng: np.random.Generator, n_images: int = 6):
    """Ground truth of 2 classes, detections near and far from it, and crowd regions per image."""
    gts, dets, ignore = [], [], []
    for _ in range(n_images):
        g = int(rng.integers(0, 6))
        xy = rng.uniform(0, 200, (g, 2))
        gb = np.concatenate([xy, xy + rng.uniform(10, 60, (g, 2))], 1)
        gc = rng.integers(0, 2, g)
        jitter = gb + rng.normal(0, 4, gb.shape)  # some match at 0.5, fewer at 0.9
        fx = rng.uniform(0, 200, (int(rng.integers(0, 5)), 2))
        false = np.concatenate([fx, fx + rng.uniform(10, 60, fx.shape)], 1)
        db = np.concatenate([jitter, false, jitter[: g // 2] + 3])  # + duplicates
        dc = np.concatenate([gc, rng.integers(0, 2, len(false)), gc[: g // 2]])
        ds = rng.uniform(0.01, 1, len(db))
        ix = rng.uniform(0, 200, (int(rng.integers(0, 2)), 2))
        ign = np.concatenate([ix, ix + rng.uniform(30, 80, ix.shape)], 1)
        db = np.concatenate([db, np.concatenate([ix + 2, ix + 22], 1)])  # a detection inside each crowd region
        dc = np.concatenate([dc, rng.integers(0, 2, len(db) - len(dc))])
        ds = np.concatenate([ds, rng.uniform(0.01, 1, len(db) - len(ds))])
        gts.append((gb, gc))
        dets.append((db, ds, dc))
        ignore.append(ign)
    return gts, dets, ignore


def _pycocotools_ap(gts, dets, ignore, cls: int) -> np.ndarray:
    """AP of category ``cls`` at each of COCO's 10 IoU thresholds; an ignore region is a crowd box of every
    category."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    def xywh(b):
        return [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]

    anns, res = [], []
    for i, ((gb, gc), (db, ds, dc), ign) in enumerate(zip(gts, dets, ignore)):
        for b, c in zip(gb, gc):
            anns.append(dict(image_id=i, category_id=int(c), bbox=xywh(b), area=xywh(b)[2] * xywh(b)[3], iscrowd=0))
        for b in ign:
            for c in (0, 1):
                anns.append(dict(image_id=i, category_id=c, bbox=xywh(b), area=xywh(b)[2] * xywh(b)[3], iscrowd=1))
        res += [dict(image_id=i, category_id=int(c), bbox=xywh(b), score=float(s)) for b, s, c in zip(db, ds, dc)]
    for k, a in enumerate(anns):
        a["id"] = k + 1
    gt = COCO()
    gt.dataset = dict(images=[dict(id=i) for i in range(len(gts))], annotations=anns,
                      categories=[dict(id=0, name="a"), dict(id=1, name="b")])
    with contextlib.redirect_stdout(io.StringIO()):
        gt.createIndex()
        ev = COCOeval(gt, gt.loadRes(res), "bbox")
        ev.params.catIds = [cls]
        ev.evaluate()
        ev.accumulate()
    return ev.eval["precision"][:, :, 0, 0, -1].mean(1)  # [T, R, K, A(all), M(100)] -> per threshold


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_average_precision_equals_pycocotools(seed):
    pytest.importorskip("pycocotools", reason="pycocotools (the dev extra) checks the AP")
    gts, dets, ignore = _random_case(np.random.default_rng(seed))
    for cls in (0, 1):
        ref = _pycocotools_ap(gts, dets, ignore, cls)
        ours = [average_precision(dets, gts, cls, t, ignore) for t in IOU_THRESHOLDS]
        np.testing.assert_allclose(ours, ref, atol=1e-6)
        assert 0 < ref[0] < 1  # a case that tests something: neither perfect nor empty


def test_match_prefers_ground_truth_then_ignores_detections_in_a_crowd_region():
    gb = np.array([[0, 0, 10, 10]], float)
    db = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60], [52, 52, 58, 58], [80, 80, 90, 90]], float)
    ds = np.array([0.5, 0.9, 0.8, 0.7, 0.6])
    gt, ign = match(db, ds, gb, 0.5, np.array([[45, 45, 65, 65]], float))
    assert gt.tolist() == [-1, 0, -1, -1, -1]  # the higher score takes the box; the exact one is a duplicate
    assert ign.tolist() == [False, False, True, True, False]


def _write_mask(path: Path, shape, boxes) -> Path:
    ids = np.zeros(shape, np.uint8)
    for k, (x1, y1, x2, y2) in enumerate(boxes, 1):
        ids[y1:y2, x1:x2] = k
    cv2.imwrite(str(path), ids)
    return path


def test_recall_precision_and_mask_iou_on_a_constructed_case(tmp_path):
    # two people: true masks are the left halves of their boxes; one vehicle
    mask = _write_mask(tmp_path / "m.png", (100, 100), [(10, 10, 20, 50), (60, 10, 70, 50)])
    rec = Record(tmp_path / "i.png", np.array([[10, 10, 30, 50], [60, 10, 80, 50], [0, 80, 40, 100]], float),
                 np.array([0, 0, 1]), np.array([[85, 85, 100, 100]], float), mask, np.array([1, 2, 0]))
    pred = Prediction(np.array([[10, 10, 30, 50], [60, 10, 80, 50], [40, 40, 50, 50], [86, 86, 99, 99],
                                [0, 80, 40, 100]], float),
                      np.array([0.9, 0.1, 0.8, 0.9, 0.3]), np.array([0, 0, 0, 0, 1]))
    rep = evaluate([rec], [pred], threshold=0.5)
    assert rep["recall/person"] == 0.5 and rep["precision/person"] == 0.5  # one found, one false, one ignored
    assert np.isnan(rep["precision/vehicle"]) and rep["recall/vehicle"] == 0.0  # below the threshold
    assert rep["AP50/vehicle"] == pytest.approx(1.0)
    assert rep["mask_iou/person"] == pytest.approx(0.5) and rep["n_masks/person"] == 1  # the box is twice the mask
    assert rep["gt_box_mask_iou/person"] == pytest.approx(0.5)
    # image: the boxes SLAM drops (800 + 100 + 169 px, the ignored one too) against the masks' 800: 400 shared
    assert rep["image_mask_iou/person"] == pytest.approx(400 / (1069 + 800 - 400))
    assert "mask_iou/vehicle" not in rep  # the vehicle has no mask (id 0): not scored


def test_fastestdet_decoding_of_one_cell():
    out = np.full((85, 22, 22), -10, np.float32)
    out[0], out[5:] = 0.0, 0.0
    out[0, 5, 7], out[5 + 2, 5, 7] = 0.8, 0.9  # cell (row 5, col 7): objectness 0.8, class 2 (car) 0.9
    out[1:5, 5, 7] = [np.arctanh(0.5), np.arctanh(-0.25), 0.0, np.log(0.25 / 0.75)]  # w 0.5, h 0.25 of the image
    boxes, scores, cls = decode(out, 440, 220, 0.1)
    assert cls.tolist() == [2] and scores[0] == pytest.approx(0.8 ** 0.6 * 0.9 ** 0.4)
    cx, cy = (7 + 0.5) / 22 * 440, (5 - 0.25) / 22 * 220
    np.testing.assert_allclose(boxes[0], [cx - 110, cy - 27.5, cx + 110, cy + 27.5], atol=1e-4)


@pytest.fixture
def penn_subset(tmp_path) -> Path:
    """The first 5 Penn-Fudan images, annotations and masks (symlinks), in the dataset's layout."""
    if not PENN.is_dir():
        pytest.skip("penn_fudan/PennFudanPed not in $VSLAM_DATA")
    root = tmp_path / "PennFudanPed"
    for sub in ("Annotation", "JPEGImages", "PedMasks"):
        (root / sub).mkdir(parents=True)
    for ann in sorted((PENN / "Annotation").glob("*.txt"))[:5]:
        for src, dst in ((ann, root / "Annotation" / ann.name),
                         (PENN / "JPEGImages" / f"{ann.stem}.jpg", root / "JPEGImages" / f"{ann.stem}.jpg"),
                         (PENN / "PedMasks" / f"{ann.stem}_mask.png", root / "PedMasks" / f"{ann.stem}_mask.png")):
            dst.symlink_to(src)
    return root


@pytest.mark.realdata
@pytest.mark.parametrize("teacher", [False, True])
def test_cli_end_to_end_on_five_images(penn_subset, tmp_path, capsys, teacher):
    if teacher:
        pytest.importorskip("onnxruntime", reason="the teacher extra (vslam[teacher]) is not installed")
        if not (data_root() / "teachers" / "fastestdet" / "FastestDet.onnx").is_file():
            pytest.skip("teachers/fastestdet not in $VSLAM_DATA")
    out = tmp_path / "r.json"
    args = ["eval-detector", str(penn_subset.parent), "--split", "all", "--threads", "1", "--json", str(out)]
    assert main(args + (["--teacher"] if teacher else [])) == 0
    text = capsys.readouterr().out
    assert "(pascal, split all, 5 images)" in text and "| person | 8 |" in text
    rep = json.loads(out.read_text())
    assert rep["images"] == 5 and rep["n_gt/person"] == 8 and rep["threshold"] == (0.5 if teacher else 0.15)
    assert 0.5 < rep["AP50/person"] <= 1 and 0 < rep["box_mask_iou/person"] <= rep["gt_box_mask_iou/person"] + 0.05
    if teacher:  # boxes only: what it masks is its box
        assert rep["mask_iou/person"] == rep["box_mask_iou/person"]
    else:  # the shipped mask head (0.57 against its boxes' 0.36 on these five)
        assert rep["mask_iou/person"] > rep["box_mask_iou/person"] + 0.12
    assert "AP50/vehicle" not in rep


def test_cli_names_a_folder_of_unknown_layout_in_one_line(tmp_path, capsys):
    (tmp_path / "photos").mkdir()
    assert main(["eval-detector", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "unknown detection layout" in err and str(tmp_path) in err


def test_a_report_read_back_from_json_renders_missing_values_as_dashes():
    """BENCHMARKS.json stores NaN (no detection at the threshold) as null; the table shows a dash."""
    rep = {"threshold": 0.15, "n_gt/person": 3, "AP50/person": 0.5, "AP50-95/person": 0.2, "recall/person": 0.0,
           "precision/person": None, "mask_iou/person": float("nan"), "box_mask_iou/person": None,
           "gt_box_mask_iou/person": 0.5, "image_mask_iou/person": 0.0}
    row = format_report(json.loads(json.dumps(rep).replace("NaN", "null")), "x")[-1]
    assert row == "| person | 3 | 0.500 | – | 0.200 | 0.000 | – | – | – | 0.500 | 0.000 |"  # no AP75 stored: a dash
