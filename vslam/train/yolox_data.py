"""Batches for fine-tuning the YOLOX-style detector (``vslam.train.yolox``).

The samples are those of the from-scratch detector's trainer (``vslam.train.detector_data.Sample``): COCO128
train2017 (``data.load_yolo``; the images whose people walk through the dynamic benchmark left out), the
train splits of Penn-Fudan and KITTI object (``datasets``, ``split_of``: never val), and copy-paste composites
(``copy_paste.paste``) of COCO / Penn-Fudan train people onto the training frames of our sequences (TUM teddy
frames before ``KeypointSplits.tum_split``, EuRoC V1_01 before ``euroc_split``). Those frames hold no people, so
every person in a composite is a pasted one: the scene's teddy bear in its yellow shirt is background there.

What differs from the old trainer is the input the network sees, which is the one it runs on
(``yolox_detector``): BGR 0..255, and the image scaled to *fit* a frame (the inference input: 416 square, or
1248x384 for KITTI) then cut to a smaller training *canvas* at a random place, so objects keep the sizes they
have at inference while a CPU step stays affordable. Scale jitter, flip and HSV jitter (``data._hsv_jitter``)
draw from the generator given; without one, the placement is the inference letterbox exactly
(``letterbox_top_left``).

A batch is a function of (seed, iteration) alone (``draw_batch``), so a run is reproducible and resumes to the
same weights. Square batches mix the sources by ``YoloxDataConfig.mix``; every ``wide_every``-th batch is a
KITTI batch on the wide canvas (one batch holds one canvas size).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vslam.dynamic.yolox_detector import PAD_VALUE, letterbox_top_left
from vslam.errors import ConfigError
from vslam.train.detector_data import Sample, _hsv_jitter, _mirrored, ignore_boxes

log = logging.getLogger(__name__)

SOURCES = ("coco", "penn_fudan", "paste")  # what a square batch mixes (KITTI object makes the wide batches)


@dataclass(frozen=True)
class YoloxDataConfig:
    """Where samples come from and how they are placed (part of ``YoloxTrainConfig``)."""

    coco: str = "coco128"  # YOLO-format folder under $VSLAM_DATA (or absolute); "" to leave out
    penn_fudan: str = "penn_fudan/PennFudanPed"
    kitti_object: str = "kitti_object/training"
    # sampling weights of the square sources (coco, penn_fudan, paste); one without samples drops out
    mix: tuple[float, float, float] = (0.25, 0.2, 0.55)
    backgrounds: tuple[str, ...] = ("tum", "euroc")  # sequence training frames people are pasted onto
    cutouts: tuple[str, ...] = ("coco", "penn_fudan")  # where pasted people come from (train splits only)
    paste_people: tuple[int, int] = (0, 3)  # inclusive; 0: a bare background frame (only negatives)
    paste_closeup: float = 0.2
    paste_tilt: float = 0.1
    paste_occluded: float = 0.2
    fit: tuple[int, int] = (416, 416)  # (w, h) the image is scaled to fit before jitter: the inference input
    canvas: tuple[int, int] = (320, 320)  # (w, h) of a square batch's images (a window of the fitted image)
    wide_fit: tuple[int, int] = (1248, 384)  # KITTI: the wide inference input
    wide_canvas: tuple[int, int] = (640, 384)
    wide_every: int = 5  # every n-th batch is a KITTI batch (0: none)
    wide_batch: int = 4
    scale: tuple[float, float] = (0.5, 1.2)  # jitter of the fitted scale

    def __post_init__(self) -> None:
        for name in ("fit", "canvas", "wide_fit", "wide_canvas"):
            w, h = getattr(self, name)
            if w <= 0 or h <= 0 or w % 32 or h % 32:
                raise ConfigError(f"train.{name} sides must be positive multiples of 32, got {w}x{h}")
        if len(self.mix) != len(SOURCES) or any(v < 0 for v in self.mix) or not sum(self.mix) > 0:
            raise ConfigError(f"train.mix: {len(SOURCES)} weights >= 0 ({', '.join(SOURCES)}), got {self.mix}")
        if self.wide_every < 0 or self.wide_batch < 1:
            raise ConfigError(f"train.wide_every >= 0 and train.wide_batch >= 1, got {self.wide_every}, "
                              f"{self.wide_batch}")
        lo, hi = self.paste_people
        if not 0 <= lo <= hi:
            raise ConfigError(f"train.paste_people is an inclusive range, got {self.paste_people}")


@dataclass
class YoloxData:
    """Labelled samples per square source, KITTI samples for the wide batches, and what composites are made of:
    unlabelled background frames and BGRA person cutouts."""

    sources: dict[str, list[Sample]]
    wide: list[Sample]
    backgrounds: list[Sample]
    cutouts: list[np.ndarray]

    def weights(self, mix: tuple[float, ...]) -> tuple[list[str], np.ndarray]:
        """(source names, probabilities) of the square sources that have samples and a weight."""
        w = dict(zip(SOURCES, mix))
        have = [n for n in SOURCES if w[n] > 0 and (n != "paste" or (self.backgrounds and self.cutouts))
                and (n == "paste" or self.sources.get(n))]
        if not have:
            raise ConfigError("train: no square training source has samples (coco, penn_fudan, paste)")
        p = np.array([w[n] for n in have], np.float64)
        return have, p / p.sum()


def place_rect(sample: Sample, canvas: tuple[int, int], fit: tuple[int, int], rng: np.random.Generator | None,
               scale: tuple[float, float] = (0.5, 1.2), min_visible: float = 0.3) -> Sample:
    """``sample`` on a ``canvas`` (w, h) grey image, scaled by r = min(fit_w / W, fit_h / H) (the inference
    letterbox to ``fit``) times a jitter drawn from ``scale``, at a random place (parts may fall off the canvas),
    flipped left-right with probability 0.5, HSV-jittered. Boxes move with the image; one cut by the canvas is
    kept if ``min_visible`` of its area is left and both sides exceed 2 px. Ignore regions move with it too.
    Without ``rng``: the inference letterbox to ``canvas`` (top-left, ``letterbox_top_left``), boxes * r.
    Masks are dropped (boxes only)."""
    img, boxes = sample.image, sample.boxes.astype(np.float64).reshape(-1, 4)
    H, W = img.shape[:2]
    cw, ch = canvas
    ign = ignore_boxes(sample)
    if rng is None:
        out, r = letterbox_top_left(img, canvas)
        sx = sy = r
        ox = oy = 0
    else:
        r = min(fit[0] / W, fit[1] / H) * rng.uniform(*scale)
        nw, nh = max(1, round(W * r)), max(1, round(H * r))
        sx, sy = nw / W, nh / H
        ox = int(rng.integers(min(0, cw - nw), max(0, cw - nw) + 1))
        oy = int(rng.integers(min(0, ch - nh), max(0, ch - nh) + 1))
        import cv2

        im = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if r < 1 else cv2.INTER_LINEAR)
        out = np.full((ch, cw, 3), PAD_VALUE, np.uint8)
        x0, y0, x1, y1 = max(ox, 0), max(oy, 0), min(ox + nw, cw), min(oy + nh, ch)
        out[y0:y1, x0:x1] = im[y0 - oy:y1 - oy, x0 - ox:x1 - ox]
    move = np.array([sx, sy, sx, sy]), np.array([ox, oy, ox, oy])
    b = boxes * move[0] + move[1]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    b = np.clip(b, 0, [cw, ch, cw, ch])
    w_, h_ = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    keep = (w_ * h_ >= min_visible * np.maximum(area, 1e-9)) & (w_ > 2) & (h_ > 2)
    b, labels = b[keep], sample.labels[keep]
    g = np.clip(ign * move[0] + move[1], 0, [cw, ch, cw, ch]) if len(ign) else ign
    g = g[(g[:, 2] > g[:, 0]) & (g[:, 3] > g[:, 1])]
    if rng is not None:
        if rng.random() < 0.5:
            out = out[:, ::-1].copy()
            b, g = _mirrored(b, cw), _mirrored(g, cw)
        out = _hsv_jitter(out, rng)
    return Sample(out, b.reshape(-1, 4), labels, None, None, g if len(g) else None)


def composite(data: YoloxData, cfg: YoloxDataConfig, person: int, rng: np.random.Generator) -> Sample:
    """A background frame (a random 4:3 window of it) with 0-3 pasted people labelled ``person``."""
    from vslam.train.copy_paste import crop_sample, paste

    bg = crop_sample(data.backgrounds[int(rng.integers(len(data.backgrounds)))], rng)
    lo, hi = cfg.paste_people
    return paste(bg, data.cutouts, person, rng, int(rng.integers(lo, hi + 1)), closeup=cfg.paste_closeup,
                 tilt=cfg.paste_tilt, occluded=cfg.paste_occluded)


@dataclass
class Batch:
    """images (B, 3, h, w) uint8 BGR (the network's input once float); per image boxes (K, 4) float32 input
    pixels x1, y1, x2, y2, labels (K,) int64, ignore regions (J, 4) float32; ``wide``: a KITTI batch."""

    images: np.ndarray
    boxes: list[np.ndarray]
    labels: list[np.ndarray]
    ignore: list[np.ndarray]
    wide: bool


def collate_bgr(samples: list[Sample], wide: bool) -> Batch:
    imgs = np.ascontiguousarray(np.stack([s.image for s in samples]).transpose(0, 3, 1, 2))
    return Batch(imgs, [s.boxes.astype(np.float32).reshape(-1, 4) for s in samples],
                 [s.labels.astype(np.int64) for s in samples],
                 [ignore_boxes(s).astype(np.float32) for s in samples], wide)


def is_wide(cfg: YoloxDataConfig, it: int, data: YoloxData) -> bool:
    return bool(data.wide) and cfg.wide_every > 0 and it % cfg.wide_every == cfg.wide_every - 1


def draw_batch(data: YoloxData, cfg: YoloxDataConfig, seed: int, it: int, batch: int, person: int) -> Batch:
    """The batch of iteration ``it``: a function of (``seed``, ``it``) alone (``np.random.default_rng``)."""
    rng = np.random.default_rng([seed, it])
    if is_wide(cfg, it, data):
        picks = rng.integers(0, len(data.wide), cfg.wide_batch)
        return collate_bgr([place_rect(data.wide[int(i)], cfg.wide_canvas, cfg.wide_fit, rng, cfg.scale)
                            for i in picks], True)
    names, p = data.weights(cfg.mix)
    out = []
    for _ in range(batch):
        src = names[int(rng.choice(len(names), p=p))]
        if src == "paste":
            s = composite(data, cfg, person, rng)
        else:
            s = data.sources[src][int(rng.integers(len(data.sources[src])))]
        out.append(place_rect(s, cfg.canvas, cfg.fit, rng, cfg.scale))
    return collate_bgr(out, False)


def _under_data(path: str) -> Path:
    from vslam.paths import data_root

    return Path(path) if Path(path).is_absolute() else data_root() / path


def load_sources(cfg: YoloxDataConfig, classes: tuple[str, ...], teacher=None, pseudo_cache: str = "",
                 pseudo_threshold: float = 0.5) -> YoloxData:
    """The training samples of ``cfg`` for a network of ``classes``; train splits only. ``teacher`` (a
    ``pseudo.Teacher``, e.g. the starting network): its boxes of people and vehicles that Penn-Fudan leaves
    unlabelled are added to the Penn-Fudan samples (``pseudo.pseudo_label``; COCO and KITTI label theirs)."""
    from vslam.data.composite import benchmark_stems, person_instances
    from vslam.paths import data_root
    from vslam.train.copy_paste import background_files, read_background
    from vslam.train.detector_data import load_yolo
    from vslam.train.keypoint_data import KeypointSplits
    from vslam.train.photos import kitti_object_samples, penn_fudan_cutouts, penn_fudan_samples

    if "person" not in classes:
        raise ConfigError(f"train: the network's classes {list(classes)} have no 'person' (composites label people)")
    sources: dict[str, list[Sample]] = {}
    cutouts: list[np.ndarray] = []
    skip: frozenset[str] = frozenset()
    if cfg.coco:
        skip = benchmark_stems(_under_data(cfg.coco))  # the benchmark's walkers: never trained on
        sources["coco"] = load_yolo(_under_data(cfg.coco), "train2017", classes, skip=skip)
        if "coco" in cfg.cutouts:
            found = person_instances(_under_data(cfg.coco), min_height_px=48, min_aspect=0.0, whole=False, exclude=skip)
            cutouts += [c for _, c in found]
    if cfg.penn_fudan:
        sources["penn_fudan"] = penn_fudan_samples(_under_data(cfg.penn_fudan), classes, "train")
        if "penn_fudan" in cfg.cutouts:
            cutouts += penn_fudan_cutouts(_under_data(cfg.penn_fudan))
        if teacher is not None:
            from vslam.train.pseudo import PseudoConfig, pseudo_label, pseudo_report

            pcfg = PseudoConfig(threshold=pseudo_threshold, cache=pseudo_cache or "runs/pseudo_cache")
            sources["penn_fudan"], stats = pseudo_label(sources["penn_fudan"], classes, pcfg, teacher, "penn_fudan")
            log.info("teacher boxes added:\n%s", pseudo_report({"penn_fudan": stats}))
    wide = kitti_object_samples(_under_data(cfg.kitti_object), classes, "train", max_side=max(cfg.wide_fit)) \
        if cfg.kitti_object and cfg.wide_every else []
    k = KeypointSplits()
    src = {"tum": (k.tum, k.tum_split, k.frame_stride), "euroc": (k.euroc, k.euroc_split, k.frame_stride)}
    unknown = set(cfg.backgrounds) - set(src)
    if unknown:
        raise ConfigError(f"train.backgrounds: unknown {sorted(unknown)} (tum, euroc: frames without people)")
    files = background_files(data_root(), {n: v for n, v in src.items() if n in cfg.backgrounds})
    imgs = [im for im in (read_background(f) for f in files) if im is not None]
    backgrounds = [Sample(im, np.zeros((0, 4)), np.zeros(0, np.int64)) for im in imgs]
    return YoloxData(sources, wide, backgrounds, cutouts)
