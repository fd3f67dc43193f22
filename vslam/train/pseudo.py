"""Teacher pseudo-labels: boxes the public FastestDet finds on training images where the labels have
none, added as boxes without a mask.

Our labelled sources leave objects out: COCO128 labels only some classes per image we train on, Penn-Fudan
leaves small or occluded people unannotated, KITTI labels no car beyond its DontCare regions. A detector trained
on them learns to call those objects background. The teacher (``vslam.train.teacher.FastestDet``) runs on each
training image; its person and vehicle boxes scoring at least ``threshold`` that overlap no labelled box (IoU
below ``max_iou`` with every box of any class) and lie mostly outside the ignore regions become boxes of the
training class ``datasets.class_index`` names (bus and truck go to the list's vehicle class). A teacher box
mostly inside a labelled box of its class, or mostly holding one, is that object too (``max_cover``): the teacher
grows a rider's box over the horse and boxes half of a labelled person. Pseudo-boxes have ``mask_valid`` False:
the teacher gives no mask. How many each source gets, and how many of them are wrong where the labels are
complete, is in docs/detector-data.md.

Teacher outputs are cached on disk, one file per image, keyed by the SHA-1 of the image's pixels, of the
teacher's ONNX file and the threshold: a rerun reads them instead of running the teacher, and gives the same
boxes. The cache holds every class the teacher reports, so changing the kept classes or the overlap rule needs
no teacher run. onnxruntime (the extra ``vslam[teacher]``) is needed only on a cache miss.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from vslam.dynamic.masking import box_intersection, box_iou
from vslam.errors import ConfigError
from vslam.train.detector_data import Sample, add_instances, ignore_boxes
from vslam.train.photos import class_index
from vslam.train.teacher import TEACHER_THRESHOLD

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PseudoConfig:
    threshold: float = TEACHER_THRESHOLD  # teacher score a pseudo-box needs
    max_iou: float = 0.5  # a teacher box with IoU at least this with a labelled box (any class) is that object
    # ... and so is one of which this fraction lies inside a labelled box of its class, or that holds this fraction
    # of one (a rider's box grown over the horse, half a labelled person); 1.0 turns the rule off
    max_cover: float = 0.7
    ignore_cover: float = 0.5  # a teacher box at least this fraction inside one ignore region is left out
    names: tuple[str, ...] = ("person", "car", "bus", "truck")  # teacher (COCO) classes turned into boxes
    min_side: float = 4.0  # pixels; thinner teacher boxes (after clipping to the image) are left out
    cache: str = "runs/pseudo_cache"  # folder of the cached teacher outputs
    teacher: str = ""  # FastestDet ONNX file; "" for $VSLAM_DATA/teachers/fastestdet/FastestDet.onnx
    threads: int = 2  # onnxruntime threads

    def __post_init__(self) -> None:
        for name in ("threshold", "max_iou", "max_cover", "ignore_cover"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"pseudo.{name} must be in (0, 1], got {getattr(self, name)}")
        if not self.cache:
            raise ConfigError("pseudo.cache: a folder for the teacher's cached outputs is needed")


class Teacher(Protocol):
    """What pseudo-labelling needs of a teacher: ``detect(image)`` -> ``detector.Detections`` (boxes, scores,
    class_names) in the image's pixels, and a ``fingerprint`` string that changes whenever its outputs could (it
    keys the cache)."""

    fingerprint: str

    def detect(self, image: np.ndarray): ...


class FastestDetTeacher:
    """FastestDet keyed by the SHA-1 of its ONNX file. The onnxruntime session is built on the first ``detect``,
    so a run served wholly from the cache needs no onnxruntime."""

    def __init__(self, path: str | Path = "", threshold: float = TEACHER_THRESHOLD, threads: int = 2):
        from vslam.train.teacher import default_teacher_path

        self.path = Path(path) if path else default_teacher_path()
        if not self.path.is_file():
            raise ConfigError(f"{self.path}: FastestDet ONNX file not found (teachers/fastestdet under $VSLAM_DATA)")
        self.fingerprint = "fastestdet-" + hashlib.sha1(self.path.read_bytes()).hexdigest()
        self.threshold, self.threads = threshold, threads
        self._model = None

    def detect(self, image: np.ndarray):
        if self._model is None:
            from vslam.train.teacher import FastestDet

            self._model = FastestDet(self.path, conf=self.threshold, threads=self.threads)
        return self._model.detect(image)


@dataclass
class PseudoStats:
    """What pseudo-labelling did on one source."""

    source: str
    images: int = 0
    boxes: int = 0  # labelled boxes already there
    teacher_runs: int = 0  # cache misses
    cache_hits: int = 0
    seconds: float = 0.0  # spent running the teacher
    added: dict[str, int] = field(default_factory=dict)  # training class name -> pseudo-boxes added
    overlapping: int = 0  # teacher boxes of a kept class left out: a labelled box there
    in_ignore: int = 0  # ... left out: inside an ignore region

    @property
    def total(self) -> int:
        return sum(self.added.values())


def teacher_outputs(image: np.ndarray, teacher: Teacher, cfg: PseudoConfig
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The teacher's detections scoring at least ``cfg.threshold`` on ``image`` (H,W,3 uint8 BGR): boxes (N,4)
    x1,y1,x2,y2 pixels, scores (N,), COCO names (N,) str, and whether they came from the cache."""
    fp = getattr(teacher, "fingerprint", None)
    if not isinstance(fp, str) or not fp:
        raise ConfigError(f"teacher {type(teacher).__name__} has no fingerprint (a string that keys the pseudo-label "
                          "cache)")
    img = np.ascontiguousarray(image)
    h = hashlib.sha1(f"{img.shape} {img.dtype}".encode())
    h.update(img.tobytes())
    key = hashlib.sha1(f"{h.hexdigest()} {fp} {cfg.threshold!r}".encode()).hexdigest()
    path = Path(cfg.cache) / key[:2] / f"{key}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return z["boxes"], z["scores"], z["names"].astype(str), True
    det = teacher.detect(img)
    boxes = np.asarray(det.boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(det.scores, np.float64).reshape(-1)
    names = np.asarray([str(n) for n in det.class_names], dtype=str).reshape(-1)
    keep = scores >= cfg.threshold
    boxes, scores, names = boxes[keep], scores[keep], names[keep]
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")  # written whole, then renamed: no torn file
    with os.fdopen(fd, "wb") as f:
        np.savez(f, boxes=boxes, scores=scores, names=names)
    os.replace(tmp, path)
    return boxes, scores, names, False


def pseudo_label(samples: list[Sample], classes: tuple[str, ...], cfg: PseudoConfig = PseudoConfig(),
                 teacher: Teacher | None = None, source: str = "") -> tuple[list[Sample], PseudoStats]:
    """``samples`` with the teacher's boxes added where no label is (module docstring), as boxes of ``classes``
    without a mask; the samples are not modified. ``teacher``: default a ``FastestDetTeacher`` of
    ``cfg.teacher``, built only when some image is not in the cache."""
    keep = {n: class_index(n, classes) for n in cfg.names}
    keep = {n: c for n, c in keep.items() if c is not None}
    stats = PseudoStats(source, added={classes[c]: 0 for c in sorted(set(keep.values()))})
    out = []
    for s in samples:
        if teacher is None:
            teacher = FastestDetTeacher(cfg.teacher, cfg.threshold, cfg.threads)
        t0 = time.perf_counter()
        boxes, _, names, hit = teacher_outputs(s.image, teacher, cfg)
        if hit:
            stats.cache_hits += 1
        else:
            stats.teacher_runs += 1
            stats.seconds += time.perf_counter() - t0
        stats.images += 1
        stats.boxes += len(s.boxes)
        new, labels = _new_boxes(s, boxes, names, keep, cfg, stats)
        out.append(add_instances(s, new, labels, None, np.zeros(len(new), bool)) if len(new) else s)
        for c in labels:
            stats.added[classes[c]] += 1
    return out, stats


def _new_boxes(s: Sample, boxes: np.ndarray, names: np.ndarray, keep: dict[str, int], cfg: PseudoConfig,
               stats: PseudoStats) -> tuple[np.ndarray, np.ndarray]:
    """The teacher boxes of kept classes that are no labelled object and lie outside the ignore regions."""
    H, W = s.image.shape[:2]
    sel = np.array([n in keep for n in names], bool)
    b = np.clip(boxes[sel].reshape(-1, 4), 0, [W, H, W, H])
    labels = np.array([keep[n] for n in names[sel]], np.int64)
    big = ((b[:, 2] - b[:, 0]) >= cfg.min_side) & ((b[:, 3] - b[:, 1]) >= cfg.min_side)
    b, labels = b[big], labels[big]
    if not len(b):
        return b, labels
    free = np.ones(len(b), bool)
    if len(s.boxes):
        same = labels[:, None] == s.labels.reshape(1, -1)
        inside, holds = _covered_fraction(b, s.boxes), _covered_fraction(s.boxes, b).T
        covered = same & ((inside >= cfg.max_cover) | (holds >= cfg.max_cover)) & (cfg.max_cover < 1.0)
        free = (box_iou(b, s.boxes).max(1) < cfg.max_iou) & ~covered.any(1)
    stats.overlapping += int((~free).sum())
    ign = ignore_boxes(s)
    if len(ign):
        inside = _covered_fraction(b, ign).max(1) >= cfg.ignore_cover
        stats.in_ignore += int((free & inside).sum())
        free &= ~inside
    return b[free], labels[free]


def _covered_fraction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,M): the fraction of box a_i's area inside box b_j."""
    area = np.maximum((a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]), 1e-12)
    return box_intersection(a, b) / area[:, None]


def pseudo_label_sources(sources: dict[str, list[Sample]], classes: tuple[str, ...],
                         cfg: PseudoConfig = PseudoConfig(), teacher: Teacher | None = None
                         ) -> tuple[dict[str, list[Sample]], dict[str, PseudoStats]]:
    """``pseudo_label`` of each named source (one teacher for all) -> (samples per source, stats per source)."""
    if teacher is None and sources:
        teacher = FastestDetTeacher(cfg.teacher, cfg.threshold, cfg.threads)
    out, stats = {}, {}
    for name, samples in sources.items():
        out[name], stats[name] = pseudo_label(samples, classes, cfg, teacher, name)
        log.info("pseudo-labels %s: %s", name, stats[name])
    return out, stats


def pseudo_report(stats: dict[str, PseudoStats]) -> str:
    """A text table: per source the images, labelled boxes, pseudo-boxes added (per class), teacher boxes left
    out, teacher runs vs cache hits and teacher seconds."""
    names = sorted({n for s in stats.values() for n in s.added})
    head = (["source", "images", "labelled", "added"] + [f"+{n}" for n in names]
            + ["overlap", "ignore", "runs", "cached", "s"])
    rows = [[s.source, s.images, s.boxes, s.total] + [s.added.get(n, 0) for n in names]
            + [s.overlapping, s.in_ignore, s.teacher_runs, s.cache_hits, f"{s.seconds:.1f}"] for s in stats.values()]
    width = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    return "\n".join("  ".join(str(x).rjust(w) for x, w in zip(r, width)) for r in [head, *rows])
