"""Readers of labelled detection folders (issue 40): Penn-Fudan (PASCAL boxes + instance masks), KITTI object
labels, YOLO (COCO128); the fixed train / val split; Penn-Fudan cutouts from the train split only."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vslam.errors import DatasetError
from vslam.paths import data_root
from vslam.train.photos import (
    EVAL_CLASSES,
    class_index,
    detect_layout,
    load_kitti_object,
    load_penn_fudan,
    load_records,
    load_yolo_records,
    penn_fudan_cutouts,
    split_of,
)

PENN = data_root() / "penn_fudan" / "PennFudanPed"
KITTI = data_root() / "kitti_object" / "training"
COCO = data_root() / "coco128"
need_penn = pytest.mark.skipif(not PENN.is_dir(), reason="penn_fudan/PennFudanPed not in $VSLAM_DATA")
need_kitti = pytest.mark.skipif(not KITTI.is_dir(), reason="kitti_object/training not in $VSLAM_DATA")
need_coco = pytest.mark.skipif(not COCO.is_dir(), reason="coco128 not in $VSLAM_DATA")
# docs/detector-data.md lists these: the split must never move
PENN_VAL = ("FudanPed00002 FudanPed00008 FudanPed00012 FudanPed00019 FudanPed00021 FudanPed00024 FudanPed00030 "
            "FudanPed00031 FudanPed00039 FudanPed00041 FudanPed00045 FudanPed00048 FudanPed00049 FudanPed00059 "
            "FudanPed00062 FudanPed00066 FudanPed00072 FudanPed00074").split()
KITTI_VAL = ("000003 000004 000010 000019 000034 000041 000043 000044 000050 000051 000056 000058 000061 000062 "
             "000064 000067 000069 000070 000072 000087 000088 000098").split()


def test_split_is_a_fixed_function_of_the_name():
    assert split_of("FudanPed00002") == "val" and split_of("FudanPed00001") == "train"
    assert split_of("000003") == "val" and split_of("000000") == "train"
    stems = [f"{i:06d}" for i in range(4000)]
    frac = np.mean([split_of(s) == "val" for s in stems])
    assert 0.22 < frac < 0.28  # about a quarter


def test_class_index_sends_every_vehicle_to_the_list_s_vehicle_class():
    assert class_index("person", EVAL_CLASSES) == 0
    assert [class_index(n, EVAL_CLASSES) for n in ("car", "bus", "truck", "motorcycle")] == [1, 1, 1, 1]
    assert [class_index(n, ("person", "car")) for n in ("car", "bus", "truck")] == [1, 1, 1]  # the shipped detector
    assert class_index("truck", ("person", "car", "truck")) == 2
    assert class_index("chair", EVAL_CLASSES) is None and class_index("car", ("person",)) is None


def _kitti_folder(root: Path, rows: list[str]) -> Path:
    (root / "image_2").mkdir(parents=True)
    (root / "label_2").mkdir()
    cv2.imwrite(str(root / "image_2" / "000003.png"), np.zeros((40, 60, 3), np.uint8))  # 000003: a val frame
    (root / "label_2" / "000003.txt").write_text("\n".join(rows) + "\n")
    return root


def test_kitti_types_map_to_person_and_vehicle_and_dontcare_is_an_ignore_region(tmp_path):
    tail = "0 0 0 0 0 0 0 0 0 0"
    root = _kitti_folder(tmp_path / "k", [f"Car 0.00 0 -1.5 1 2 11 12 {tail}", f"Cyclist 0.0 0 0 3 4 5 6 {tail}",
                                          f"Tram 0 0 0 7 8 9 10 {tail}", f"DontCare -1 -1 -10 20 21 30 31 {tail}",
                                          f"Misc 0 0 0 40 1 50 9 {tail}"])
    assert detect_layout(tmp_path)[0] == "kitti"  # the parent folder is accepted too
    (rec,) = load_kitti_object(root, "val")
    np.testing.assert_array_equal(rec.boxes, [[1, 2, 11, 12], [3, 4, 5, 6], [7, 8, 9, 10]])
    assert list(rec.labels) == [1, 0, 1]
    np.testing.assert_array_equal(rec.ignore, [[20, 21, 30, 31], [40, 1, 50, 9]])
    assert load_kitti_object(root, "all", ("person", "car"))[0].labels.tolist() == [1, 0, 1]
    with pytest.raises(DatasetError, match="no images in split 'train'"):
        load_kitti_object(root, "train")
    (root / "label_2" / "000003.txt").write_text(f"Boat 0 0 0 1 2 3 4 {tail}\n")
    with pytest.raises(DatasetError, match="000003.txt:1: unknown KITTI object type 'Boat'"):
        load_kitti_object(root, "all")


def test_unknown_layout_is_a_dataset_error(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(DatasetError, match="unknown detection layout"):
        detect_layout(tmp_path)


def test_yolo_names_and_label_errors_name_the_file_and_line(tmp_path):
    root = tmp_path / "yolo"
    (root / "images" / "val2017").mkdir(parents=True)
    (root / "labels" / "val2017").mkdir(parents=True)
    cv2.imwrite(str(root / "images" / "val2017" / "a.jpg"), np.zeros((40, 60, 3), np.uint8))
    lab = root / "labels" / "val2017" / "a.txt"
    lab.write_text("0 0.5 0.5 0.2 0.4\n\n2 0.25 0.5 0.1 0.2\n")
    (root / "names.yaml").write_text("path: .\n")  # no names
    with pytest.raises(DatasetError, match=r"names.yaml: missing key 'names' \(the class names"):
        load_yolo_records(root, "val")
    (root / "names.yaml").write_text("names: [person, bicycle, car]\n")
    (rec,) = load_yolo_records(root, "val")
    np.testing.assert_allclose(rec.boxes, [[24, 12, 36, 28], [12, 16, 18, 24]])
    assert rec.labels.tolist() == [0, 1]
    lab.write_text("0 0.5 0.5 0.2 0.4\n1 0.5 oops 0.1\n")
    with pytest.raises(DatasetError, match=r"a.txt:2: a label row is 'class cx cy w h'.*got '1 0.5 oops 0.1'"):
        load_yolo_records(root, "val")
    lab.write_text("0.5 0.5 0.5 0.2 0.4\n")
    with pytest.raises(DatasetError, match=r"a.txt:1: a label row is 'class cx cy w h' \(class an integer id"):
        load_yolo_records(root, "val")


@need_penn
def test_penn_fudan_counts_split_and_masks():
    every = load_penn_fudan(PENN, "all")
    assert len(every) == 74 and sum(len(r.boxes) for r in every) == 160
    assert all(r.path.suffix == ".jpg" and r.path.is_file() for r in every)  # the annotation names PNGImages/*.png
    train, val = load_penn_fudan(PENN, "train"), load_penn_fudan(PENN, "val")
    assert [r.stem for r in val] == PENN_VAL
    assert not {r.stem for r in train} & set(PENN_VAL)
    assert len(train) + len(val) == 74 and sum(len(r.boxes) for r in val) == 37
    for r in every:
        masks = r.masks()
        assert masks.shape[0] == len(r.boxes) and masks.shape[1:] == r.image().shape[:2]
        for box, m in zip(r.boxes, masks):
            ys, xs = np.nonzero(m)
            np.testing.assert_allclose([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], box, atol=2)


@need_penn
def test_penn_fudan_cutouts_come_from_the_train_split_only():
    cuts = penn_fudan_cutouts(PENN)
    n_train = sum(len(r.boxes) for r in load_penn_fudan(PENN, "train"))
    assert 0.9 * n_train <= len(cuts) <= n_train  # pedestrians under 48 px are left out
    assert all(c.shape[2] == 4 and c[..., 3].max() == 255 for c in cuts)


@need_kitti
def test_kitti_object_counts_and_split():
    every = load_kitti_object(KITTI, "all")
    assert len(every) == 101
    labels = np.concatenate([r.labels for r in every])
    # README: Pedestrian 47 + Person_sitting 5 + Cyclist 18; Car 303 + Van 34 + Truck 14 + Tram 12
    assert np.bincount(labels).tolist() == [70, 363]
    assert sum(len(r.ignore) for r in every) == 237 + 6  # DontCare + Misc
    val = load_kitti_object(KITTI, "val")
    assert [r.stem for r in val] == KITTI_VAL
    assert not {r.stem for r in load_kitti_object(KITTI, "train")} & set(KITTI_VAL)


@need_coco
def test_coco128_keeps_its_folders_as_the_split():
    val = load_yolo_records(COCO, "val")
    assert len(val) == 128 and all(r.path.parent.name == "val2017" for r in val)
    layout, train = load_records(COCO, "train")
    assert layout == "yolo" and all(r.path.parent.name == "train2017" for r in train)
    # 611 person labels in the folder, 7 of them in two label files whose images are not there
    assert sum(int((r.labels == 0).sum()) for r in val + train) == 604
