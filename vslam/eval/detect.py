"""``vslam detect IMAGES... -o dets.json``: a detector's boxes on image files, in COCO's results format.

The output is a JSON list with one entry per detection, as ``pycocotools``' ``COCO.loadRes`` reads it:
``image_id`` (the file stem as an integer where it is one, as COCO's own file names are, else the image's
position in the order given), ``category_id`` (COCO's category id of the class name; 1000 + the class index for
a name COCO lacks), ``bbox`` [x, y, width, height] in image pixels, ``score``; plus ``file_name`` and
``category_name`` for a reader without the COCO annotations, and ``segmentation`` (an uncompressed RLE,
column-major as COCO's) where the detector gives instance masks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from vslam.errors import ConfigError, DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def image_files(paths: Iterable[str | Path]) -> list[Path]:
    """The image files named, folders expanded to their images (sorted); a missing path is a one-line error."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        elif p.is_file():
            out.append(p)
        else:
            raise ConfigError(f"{p}: no such image or folder")
    if not out:
        raise ConfigError("no images to detect on (give image files or folders of .png / .jpg)")
    return out


def category_id(name: str, index: int) -> int:
    from vslam.nn.detectors.coco import COCO80
    from vslam.train.detector_data import COCO80_TO_91

    return COCO80_TO_91[COCO80.index(name)] if name in COCO80 else 1000 + index


def rle(mask: np.ndarray) -> dict[str, Any]:
    """(H, W) bool -> COCO's uncompressed RLE: run lengths over the column-major pixels, starting with zeros."""
    flat = np.asarray(mask, bool).ravel(order="F")
    edges = np.flatnonzero(np.diff(flat.astype(np.int8))) + 1
    runs = np.diff(np.concatenate([[0], edges, [flat.size]]))
    counts = ([0] if flat.size and flat[0] else []) + runs.tolist()
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": [int(c) for c in counts]}


def coco_results(detector: Any, files: list[Path], threshold: float,
                 progress: Callable[[int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run ``detector`` (``detect(image) -> Detections``) on ``files``; detections scoring >= ``threshold`` as
    COCO result entries (module docstring)."""
    import cv2

    out: list[dict[str, Any]] = []
    for n, f in enumerate(files):
        image = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f, "does not decode as an image")
        d = detector.detect(image)
        image_id = int(f.stem) if f.stem.isdigit() else n
        for k in np.flatnonzero(np.asarray(d.scores) >= threshold):
            x1, y1, x2, y2 = (float(v) for v in d.boxes[k])
            name = str(d.class_names[k])
            entry = {"image_id": image_id, "file_name": str(f), "category_id": category_id(name, int(d.class_ids[k])),
                     "category_name": name, "bbox": [round(x1, 2), round(y1, 2), round(x2 - x1, 2), round(y2 - y1, 2)],
                     "score": round(float(d.scores[k]), 5)}
            if d.masks is not None:
                entry["segmentation"] = rle(d.masks[k])
            out.append(entry)
        if progress is not None:
            progress(n + 1, len(files))
    return out
