"""Labelled detection folders for training and evaluation: YOLO (COCO128), PASCAL-style Penn-Fudan
(boxes + per-instance masks) and KITTI object labels, each with a fixed train / val split.

A record is one image with its boxes, read lazily (``Record.image()``, ``Record.masks()``): the evaluator streams
a few hundred full-size photos without holding them. Classes are resolved by name against the caller's list
(``class_index``): the evaluator's ``("person", "vehicle")``, or a detector's ``("person", "car")`` where every
vehicle becomes ``car``.

Split (``split_of``, docs/detector-data.md): an image is in ``val`` when the SHA-1 of its file stem, read as an
integer, is divisible by 4 (about a quarter), else in ``train``. It depends on the name alone, so it is the same
on every machine and for every subset of a folder, and a frame keeps its side when the full dataset is added.
COCO128 keeps its own folders: ``train2017`` is train, ``val2017`` is val. Validation images are never trained on
and never cut out for copy-paste (``penn_fudan_cutouts`` reads the train split only).

Training samples (``record_sample``, ``penn_fudan_samples``, ``kitti_object_samples``): a record's image downscaled
as ``data.load_yolo`` does, with its boxes, its instance masks where the source has them (Penn-Fudan) and its
ignore regions (KITTI DontCare / Misc).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from vslam.errors import ConfigError, DatasetError
from vslam.train.detector_data import Sample, resize_masks

Split = Literal["train", "val", "all"]
Layout = Literal["yolo", "pascal", "kitti"]
EVAL_CLASSES = ("person", "vehicle")
# the vehicle names of DynamicConfig.classes (COCO names): SLAM masks all of them
VEHICLES = ("car", "bus", "truck", "motorcycle")
# KITTI object label -> COCO name. A cyclist is a person on a bicycle (the person is what moves and is masked);
# a tram is a large road vehicle (COCO has no tram; SLAM masks buses). DontCare and Misc become ignore regions.
KITTI_CLASSES = {"Pedestrian": "person", "Person_sitting": "person", "Cyclist": "person", "Car": "car", "Van": "car",
                 "Truck": "truck", "Tram": "bus"}
KITTI_IGNORE = ("DontCare", "Misc")
VAL_MODULUS = 4


@dataclass
class Record:
    """One labelled image. boxes: (K,4) float64 x1,y1,x2,y2 pixels of the full image (x2, y2 exclusive: a box of
    pixel columns 0..9 is 0..10); labels: (K,) int64 into the reader's ``classes``; ignore: (M,4) regions where a
    detection is neither right nor wrong (KITTI DontCare / Misc); mask_path: instance-id image (pixel value k =
    object k) with ``mask_ids`` (K,) the id of each box (0: that box has no mask), or None."""

    path: Path
    boxes: np.ndarray
    labels: np.ndarray
    ignore: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    mask_path: Path | None = None
    mask_ids: np.ndarray | None = None

    @property
    def stem(self) -> str:
        return self.path.stem

    def image(self) -> np.ndarray:
        """(H,W,3) uint8 BGR."""
        img = cv2.imread(str(self.path), cv2.IMREAD_COLOR)
        if img is None:
            raise DatasetError(self.path, "does not decode as an image")
        return img

    def masks(self) -> np.ndarray | None:
        """(K,H,W) bool, one per box (all False for a box of id 0), or None where the source has no masks."""
        if self.mask_path is None or self.mask_ids is None:
            return None
        ids = cv2.imread(str(self.mask_path), cv2.IMREAD_UNCHANGED)
        if ids is None:
            raise DatasetError(self.mask_path, "does not decode as an image")
        return (ids[None] == self.mask_ids.reshape(-1, 1, 1)) & (self.mask_ids > 0).reshape(-1, 1, 1)


def split_of(stem: str) -> Literal["train", "val"]:
    """The fixed split of an image by its file stem (module docstring)."""
    return "val" if int(hashlib.sha1(stem.encode()).hexdigest(), 16) % VAL_MODULUS == 0 else "train"


def _in_split(stem: str, split: Split) -> bool:
    if split not in ("train", "val", "all"):
        raise ConfigError(f"split must be train, val or all, got {split!r}")
    return split == "all" or split_of(stem) == split


def class_index(name: str, classes: tuple[str, ...]) -> int | None:
    """A COCO-style name (person, car, bus, ...) -> its index in ``classes``, or None. A vehicle goes to
    ``vehicle`` where the list has it, else to its own name, else to ``car`` (a detector's one vehicle class)."""
    if name in VEHICLES:
        for cand in ("vehicle", name, "car"):
            if cand in classes:
                return classes.index(cand)
        return None
    return classes.index(name) if name in classes else None


def detect_layout(root: str | Path) -> tuple[Layout, Path]:
    """-> (layout, the folder that holds it). Accepts the dataset folder or its parent (``penn_fudan`` ->
    ``PennFudanPed``, ``kitti_object`` -> ``training``)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "not a folder")
    for cand in [root] + sorted(p for p in root.iterdir() if p.is_dir()):
        if (cand / "images").is_dir() and (cand / "labels").is_dir():
            return "yolo", cand
        if (cand / "Annotation").is_dir() and ((cand / "JPEGImages").is_dir() or (cand / "PNGImages").is_dir()):
            return "pascal", cand
        if (cand / "image_2").is_dir() and (cand / "label_2").is_dir():
            return "kitti", cand
    raise DatasetError(root, "unknown detection layout (expected images/ + labels/ (YOLO), Annotation/ + JPEGImages/ "
                             "(PASCAL, Penn-Fudan) or image_2/ + label_2/ (KITTI object))")


def load_records(root: str | Path, split: Split, classes: tuple[str, ...] = EVAL_CLASSES) -> tuple[Layout, list[Record]]:
    """Any of the three layouts (``detect_layout``) -> (layout, records of ``split``)."""
    layout, folder = detect_layout(root)
    reader = {"yolo": load_yolo_records, "pascal": load_penn_fudan, "kitti": load_kitti_object}[layout]
    return layout, reader(folder, split, classes)


# --- YOLO (COCO128) ------------------------------------------------------------------------------------------

def _yolo_names(root: Path) -> list[str]:
    import yaml

    path = root / "names.yaml"
    if not path.is_file():
        raise DatasetError(path, "missing (a YOLO dataset needs names.yaml)")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise DatasetError(path, f"not valid YAML ({str(e).splitlines()[0]})") from None
    names = data.get("names") if isinstance(data, dict) else None
    if not isinstance(names, (dict, list)) or not names:
        raise DatasetError(path, "missing key 'names' (the class names: a list, or a mapping of class id to name)")
    return [names[i] for i in sorted(names)] if isinstance(names, dict) else list(names)


def _yolo_labels(path: Path) -> np.ndarray:
    """(N, 5) rows ``class cx cy w h`` of a YOLO label file; DatasetError naming the file and line of a bad row."""
    rows = []
    for ln, text in enumerate(path.read_text().splitlines(), 1):
        if not text.strip():
            continue
        parts = text.split()
        try:
            row = [float(x) for x in parts]
        except ValueError:
            row = []
        if len(row) != 5 or not all(np.isfinite(row)) or row[0] != int(row[0]) or row[0] < 0:
            raise DatasetError(path, f"a label row is 'class cx cy w h' (class an integer id, the box normalised), "
                                     f"got {text.strip()!r}", ln)
        rows.append(row)
    return np.asarray(rows, np.float64).reshape(-1, 5)


def load_yolo_records(root: str | Path, split: Split, classes: tuple[str, ...] = EVAL_CLASSES) -> list[Record]:
    """``images/<sub>/*.jpg`` + ``labels/<sub>/*.txt`` (class cx cy w h, normalised). Subfolders named *val* are
    the val split and the others train (COCO128: val2017 / train2017); images directly in ``images/`` are split by
    ``split_of``. Boxes of classes not in ``classes`` are dropped."""
    root = Path(root)
    names = _yolo_names(root)
    ours = {i: class_index(n, classes) for i, n in enumerate(names)}
    out = []
    for img in sorted(p for p in (root / "images").rglob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png")):
        sub = img.parent.relative_to(root / "images")
        if sub.parts:
            side = "val" if "val" in sub.parts[0].lower() else "train"
            if split != "all" and side != split:
                continue
        elif not _in_split(img.stem, split):
            continue
        lab = (root / "labels" / sub / img.stem).with_suffix(".txt")
        rows = _yolo_labels(lab) if lab.is_file() else np.zeros((0, 5))
        rows = rows[[ours.get(int(c)) is not None for c in rows[:, 0]]] if len(rows) else rows
        h, w = _image_size(img)
        cx, cy, bw, bh = rows[:, 1] * w, rows[:, 2] * h, rows[:, 3] * w, rows[:, 4] * h
        boxes = np.stack([cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], 1).reshape(-1, 4)
        out.append(Record(img, boxes, np.array([ours[int(c)] for c in rows[:, 0]], np.int64)))
    return _non_empty(out, root / "images", split)


def _image_size(path: Path) -> tuple[int, int]:
    """(height, width) from the file header (PIL reads no pixels)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.height, im.width
    except (OSError, UnidentifiedImageError) as e:
        raise DatasetError(path, f"does not open as an image ({e})") from None


def _non_empty(records: list[Record], where: Path, split: str) -> list[Record]:
    if not records:
        raise DatasetError(where, f"no images in split {split!r}")
    return records


# --- PASCAL (Penn-Fudan) -------------------------------------------------------------------------------------

_PASCAL_BOX = re.compile(r'Bounding box for object (\d+).*:\s*\((\d+),\s*(\d+)\)\s*-\s*\((\d+),\s*(\d+)\)')
_PASCAL_FILE = re.compile(r'Image filename\s*:\s*"([^"]+)"')


def load_penn_fudan(root: str | Path, split: Split, classes: tuple[str, ...] = EVAL_CLASSES) -> list[Record]:
    """``Annotation/*.txt`` (PASCAL Annotation 1.00 text) with ``JPEGImages/`` (or ``PNGImages/``) and
    ``PedMasks/<stem>_mask.png`` (pixel value k = pedestrian k). The annotation names ``PNGImages/<stem>.png``;
    the image is looked up by stem, so a JPEG re-encoding reads the same. PASCAL corners are 1-based and
    inclusive: (Xmin, Ymin) - (Xmax, Ymax) becomes x1 = Xmin - 1 .. x2 = Xmax (exclusive, 0-based)."""
    root = Path(root)
    person = class_index("person", classes)
    if person is None:
        raise ConfigError(f"Penn-Fudan labels people; the class list {list(classes)} has no person")
    out = []
    for ann in sorted((root / "Annotation").glob("*.txt")):
        text = ann.read_text(errors="replace")
        m = _PASCAL_FILE.search(text)
        if not m:
            raise DatasetError(ann, "no 'Image filename' line (not a PASCAL Annotation 1.00 file)")
        stem = Path(m.group(1)).stem
        if not _in_split(stem, split):
            continue
        img = next((root / d / (stem + e) for d in ("JPEGImages", "PNGImages") for e in (".jpg", ".png")
                    if (root / d / (stem + e)).is_file()), None)
        if img is None:
            raise DatasetError(ann, f"its image {stem} is in neither JPEGImages/ nor PNGImages/")
        found = [(int(k), *map(float, xy)) for k, *xy in _PASCAL_BOX.findall(text)]
        boxes = np.array([[x1 - 1, y1 - 1, x2, y2] for _, x1, y1, x2, y2 in found], np.float64).reshape(-1, 4)
        mask = root / "PedMasks" / f"{stem}_mask.png"
        out.append(Record(img, boxes, np.full(len(boxes), person, np.int64), mask_path=mask if mask.is_file() else None,
                          mask_ids=np.array([k for k, *_ in found], np.int64)))
    return _non_empty(out, root / "Annotation", split)


def penn_fudan_cutouts(root: str | Path, min_height_px: int = 48) -> list[np.ndarray]:
    """BGRA crops of the Penn-Fudan pedestrians of the train split (alpha from their masks) for copy-paste:
    never from val. Same form as ``composite.person_instances``."""
    out = []
    for rec in load_penn_fudan(root, "train", ("person",)):
        img, masks = rec.image(), rec.masks()
        if masks is None:
            continue
        for m in masks:
            ys, xs = np.nonzero(m)
            if len(ys) == 0 or ys.max() + 1 - ys.min() < min_height_px:
                continue
            y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            alpha = (m[y0:y1, x0:x1] * 255).astype(np.uint8)
            out.append(np.dstack([img[y0:y1, x0:x1], alpha]))
    return out


# --- KITTI object --------------------------------------------------------------------------------------------

def load_kitti_object(root: str | Path, split: Split, classes: tuple[str, ...] = EVAL_CLASSES) -> list[Record]:
    """``label_2/<stem>.txt`` (KITTI's 15 columns: type, truncated, occluded, alpha, left, top, right, bottom, ...)
    with ``image_2/<stem>.{png,jpg}``. Types map by ``KITTI_CLASSES``; DontCare and Misc boxes are the ignore
    regions; a type outside both is an error (a label file of another dataset)."""
    root = Path(root)
    out = []
    for lab in sorted((root / "label_2").glob("*.txt")):
        if not _in_split(lab.stem, split):
            continue
        img = next((p for e in (".png", ".jpg") if (p := root / "image_2" / (lab.stem + e)).is_file()), None)
        if img is None:
            raise DatasetError(lab, f"no image_2/{lab.stem}.png or .jpg")
        boxes, labels, ignore = [], [], []
        for n, line in enumerate(lab.read_text().splitlines(), 1):
            v = line.split()
            if not v:
                continue
            if len(v) < 8:
                raise DatasetError(lab, f"{len(v)} columns, a KITTI label has 15", n)
            box = [float(x) for x in v[4:8]]
            if v[0] in KITTI_IGNORE:
                ignore.append(box)
            elif v[0] in KITTI_CLASSES:
                c = class_index(KITTI_CLASSES[v[0]], classes)
                if c is not None:
                    boxes.append(box)
                    labels.append(c)
            else:
                raise DatasetError(lab, f"unknown KITTI object type {v[0]!r}", n)
        out.append(Record(img, np.array(boxes, np.float64).reshape(-1, 4), np.array(labels, np.int64),
                          np.array(ignore, np.float64).reshape(-1, 4)))
    return _non_empty(out, root / "label_2", split)


# --- training samples ----------------------------------------------------------------------------------------

def record_sample(rec: Record, max_side: int = 640) -> Sample:
    """A record as a training ``Sample``: the image downscaled so its longer side is at most ``max_side``, boxes
    and ignore regions scaled with it, and the instance masks where the source has them (``mask_valid`` False for
    a box without one: id 0, an empty mask, or a source without masks)."""
    img = rec.image()
    h, w = img.shape[:2]
    r = min(1.0, max_side / max(h, w))
    masks = rec.masks()
    if masks is not None and masks.shape[1:] != (h, w):
        raise DatasetError(rec.mask_path or rec.path, f"mask {masks.shape[2]}x{masks.shape[1]} is not the size of "
                                                      f"its image {rec.path.name} ({w}x{h})")
    if r < 1.0:
        nw, nh = round(w * r), round(h * r)
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        masks = resize_masks(masks, nw, nh) if masks is not None else None
    k = len(rec.boxes)
    valid = np.zeros(k, bool) if masks is None else masks.any(axis=(1, 2))
    ignore = rec.ignore.astype(np.float64).reshape(-1, 4) * r
    return Sample(img, rec.boxes.astype(np.float64).reshape(-1, 4) * r, rec.labels.astype(np.int64),
                  masks if valid.any() else None, valid, ignore if len(ignore) else None)


def penn_fudan_samples(root: str | Path, classes: tuple[str, ...], split: Split = "train",
                       max_side: int = 640) -> list[Sample]:
    """Penn-Fudan pedestrians of ``split`` (train for training: never val) with their instance masks."""
    return [record_sample(r, max_side) for r in load_penn_fudan(root, split, classes)]


def kitti_object_samples(root: str | Path, classes: tuple[str, ...], split: Split = "train",
                         max_side: int = 640) -> list[Sample]:
    """KITTI object frames of ``split`` (train for training: never val): boxes without masks (``mask_valid``
    False), DontCare / Misc as ``ignore``."""
    return [record_sample(r, max_side) for r in load_kitti_object(root, split, classes)]
