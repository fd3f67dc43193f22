"""``vslam train yolox-masks``: the box-prompted mask head of ``YOLOXMasks`` over a frozen YOLOX detector.

Only the mask head learns: the YOLOX backbone, neck, box head and their BatchNorm statistics are the ``init``
checkpoint's (by default the shipped ``yolox_nano_slam.pt``), so the trained model's boxes are the source's bit for
bit. The head is prompted with each instance's true box, jittered as a detector's box would be (``jitter``), and
learns the instance's mask in it (binary cross-entropy + Dice on the RoIAligned mask).

Data (train splits only, ``vslam.train.detector.training_data`` with its copy-paste recipe): COCO128 train2017
instance polygons (the benchmark's walkers held out), Penn-Fudan train people with their masks, KITTI object train
boxes, and composites: COCO / Penn-Fudan people pasted onto COCO, TUM and EuRoC training frames (exact masks).
Person boxes without a mask (KITTI, COCO crowd boxes) of at least ``teacher_min_px`` height get the BlazePose-lite
teacher's pseudo-mask (``vslam.train.mask_teacher``, cached under ``teacher_cache``); smaller ones are not trained.

Seeded (batch ``it`` is a function of (seed, it) alone); ``out/last.pt`` every ``ckpt_every`` iterations, read
weights-only on ``resume``. Outputs in ``out``: last.pt, model.pt (the whole network, ``vslam.nn.checkpoint``
format, arch ``yolox-nano-masks``), log.csv, metrics.json. ``toy``: random small network on synthetic shapes, a
smoke test of the loop on CPU.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from vslam.errors import ConfigError
from vslam.progress import Progress
from vslam.train.detector_data import Sample, mask_validity

log = logging.getLogger(__name__)
ARCH = "yolox-nano-masks"
THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)  # mask probability cuts tried by ``pick_threshold``


@dataclass(frozen=True)
class MaskTrainConfig:
    out: str = "runs/train_yolox_masks"
    init: str = ""  # the YOLOX checkpoint whose boxes the head serves ("": the shipped yolox_nano_slam.pt)
    mask: dict[str, Any] = field(default_factory=dict)  # mask head conf over MASK_DEFAULTS (roi, side, ...)
    coco: str = "coco128"  # relative to $VSLAM_DATA or absolute; "" to leave out
    penn_fudan: str = "penn_fudan/PennFudanPed"
    kitti_object: str = "kitti_object/training"
    copy_paste: float = 0.4  # probability that a sample is a composite (people pasted onto a training frame)
    cutouts: tuple[str, ...] = ("coco", "penn_fudan")
    paste_closeup: float = 0.15
    paste_tilt: float = 0.2
    paste_occluded: float = 0.2
    teacher: bool = True  # pseudo-masks for person boxes without one
    teacher_min_px: float = 40.0
    teacher_cache: str = "runs/mask_teacher_cache"
    img_size: int = 416  # square training canvas (the detector's input size)
    batch: int = 8
    iterations: int = 3000
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: int = 100
    jitter: float = 0.04  # std of each box side's shift, as a fraction of the box's width / height
    min_box_px: float = 12.0  # instances smaller on the canvas are not trained
    max_rois: int = 48  # per batch (the largest kept)
    dice: float = 1.0  # weight of the Dice term beside the cross-entropy
    seed: int = 0
    threads: int = 1
    ckpt_every: int = 100
    log_every: int = 20
    weights: str = ""  # also write the final model here (float16), e.g. vslam/models/<name>.pt
    evaluate: bool = True  # mask IoU on Penn-Fudan val at the end
    pick_threshold: bool = True  # ... after choosing the mask threshold on Penn-Fudan train (``THRESHOLDS``)
    resume: bool = False
    device: str = "cpu"  # cpu | cuda | auto
    toy: bool = False

    def __post_init__(self) -> None:
        if self.img_size % 32 or self.img_size <= 0:
            raise ConfigError(f"train.img_size must be a positive multiple of 32, got {self.img_size}")
        if not 0.0 <= self.copy_paste <= 1.0:
            raise ConfigError(f"train.copy_paste is a probability (0-1), got {self.copy_paste}")
        if self.batch < 1 or self.iterations < 1 or self.max_rois < 1:
            raise ConfigError("train.batch, train.iterations and train.max_rois must be >= 1")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device must be auto, cpu or cuda, got {self.device!r}")


TOY = dict(img_size=128, batch=2, iterations=30, ckpt_every=10, log_every=5, warmup=5, lr=5e-3, evaluate=False,
           teacher=False, mask={"roi": 7, "side": 28, "channels": 16, "image_channels": 8})


def _recipe(cfg: dict) -> dict:
    """What a resumed run must share with the first: everything but where / how long / how it is reported."""
    return {k: v for k, v in cfg.items() if k not in ("out", "iterations", "resume", "evaluate", "weights", "ckpt_every",
                                                      "log_every", "threads", "device", "pick_threshold")}


# --- data ----------------------------------------------------------------------------------------------------

@dataclass
class MaskData:
    samples: list[Sample]
    backgrounds: list[Sample]
    cutouts: list[np.ndarray]
    detector_cfg: Any  # the copy-paste recipe (``vslam.train.detector.TrainConfig``) that draws from them


def _with_teacher(s: Sample, person: int, teacher: Any, cfg: MaskTrainConfig) -> Sample:
    """``s`` with the teacher's masks for its person boxes of at least ``teacher_min_px`` height that have none."""
    from vslam.train.mask_teacher import cached_masks

    valid = mask_validity(s)
    h = s.boxes[:, 3] - s.boxes[:, 1] if len(s.boxes) else np.zeros(0)
    todo = np.flatnonzero(~valid & (s.labels == person) & (h >= cfg.teacher_min_px))
    if not len(todo):
        return s
    name = hashlib.sha1(s.image.tobytes()).hexdigest()
    pm = cached_masks(teacher, s.image, s.boxes[todo], name, cfg.teacher_cache)
    masks = s.masks.copy() if s.masks is not None else np.zeros((len(s.boxes), *s.image.shape[:2]), bool)
    masks[todo] = pm
    valid = valid.copy()
    valid[todo] = pm.any(axis=(1, 2))
    return Sample(s.image, s.boxes, s.labels, masks, valid, s.ignore)


def training_data(cfg: MaskTrainConfig, classes: tuple[str, ...]) -> MaskData:
    """The samples, backgrounds and cutouts of the detector trainer's copy-paste recipe, person boxes without
    masks filled in by the teacher (``teacher``)."""
    from vslam.train.detector import TrainConfig
    from vslam.train.detector import training_data as detector_data

    dc = TrainConfig(classes=classes, coco=cfg.coco, synthetic_seeds=(), img_size=cfg.img_size, masks=32,
                     copy_paste=cfg.copy_paste, penn_fudan=cfg.penn_fudan, kitti_object=cfg.kitti_object,
                     cutouts=cfg.cutouts, paste_closeup=cfg.paste_closeup, paste_tilt=cfg.paste_tilt,
                     paste_occluded=cfg.paste_occluded, seed=cfg.seed, evaluate=False)
    d = detector_data(dc)
    samples, backgrounds = d.samples, d.backgrounds
    if cfg.teacher and "person" in classes:
        from vslam.train.mask_teacher import BlazePoseTeacher

        teacher = BlazePoseTeacher(threads=max(1, cfg.threads))
        person = classes.index("person")
        done = {id(s): _with_teacher(s, person, teacher, cfg) for s in samples + backgrounds}
        samples, backgrounds = [done[id(s)] for s in samples], [done[id(s)] for s in backgrounds]
    return MaskData(samples, backgrounds, d.cutouts, dc)


def toy_samples(n: int, size: int, rng: np.random.Generator) -> list[Sample]:
    """Synthetic frames: noise with 1-3 filled ellipses (label 0), their exact masks."""
    out = []
    for _ in range(n):
        img = rng.integers(0, 255, (size, size, 3)).astype(np.uint8)
        boxes, masks = [], []
        for _ in range(int(rng.integers(1, 4))):
            m = np.zeros((size, size), np.uint8)
            c = tuple(int(v) for v in rng.integers(size // 4, 3 * size // 4, 2))
            ax = tuple(int(v) for v in rng.integers(size // 10, size // 4, 2))
            cv2.ellipse(m, c, ax, float(rng.uniform(0, 180)), 0, 360, 1, -1)
            img[m > 0] = rng.integers(0, 255, 3).astype(np.uint8)
            ys, xs = np.nonzero(m)
            boxes.append([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
            masks.append(m > 0)
        out.append(Sample(img, np.array(boxes, np.float64), np.zeros(len(boxes), np.int64), np.array(masks)))
    return out


def draw_batch(data: MaskData, cfg: MaskTrainConfig, it: int) -> list[Sample]:
    """The samples of iteration ``it`` on the ``img_size`` canvas: a function of (seed, it) alone."""
    from vslam.train.detector import TrainData, draw_sample
    from vslam.train.detector_data import place

    rng = np.random.default_rng([cfg.seed, it])
    if data.detector_cfg is None:
        return [place(data.samples[int(rng.integers(len(data.samples)))], cfg.img_size, rng) for _ in range(cfg.batch)]
    td = TrainData(data.samples, data.backgrounds, data.cutouts)
    return [draw_sample(td, data.detector_cfg, rng) for _ in range(cfg.batch)]


def roi_targets(samples: list[Sample], cfg: MaskTrainConfig, side: int, margin: float,
                rng: np.random.Generator) -> tuple[list[torch.Tensor], torch.Tensor]:
    """-> per sample the jittered prompt boxes (K_b, 4) of its trained instances, and their targets (sum K_b, side,
    side) float: each instance's mask RoIAligned over its grown prompt box (the head's region)."""
    from torchvision.ops import roi_align

    from vslam.nn.detectors.yolox_masks import expand_boxes

    boxes, targets = [], []
    for s in samples:
        b = s.boxes.reshape(-1, 4)
        wh = np.stack([b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], 1)
        keep = np.flatnonzero(mask_validity(s) & (wh.min(1) >= cfg.min_box_px)) if len(b) else np.zeros(0, int)
        if len(keep) and s.masks is not None:
            jb = b[keep] + rng.normal(0.0, cfg.jitter, (len(keep), 4)) * np.tile(wh[keep], 2)
            jb = torch.from_numpy(jb).float()
            m = torch.from_numpy(s.masks[keep]).float()[:, None]
            rois = torch.cat([torch.arange(len(keep), dtype=torch.float32)[:, None], expand_boxes(jb, margin)], 1)
            targets.append(roi_align(m, rois, side, 1.0, sampling_ratio=2, aligned=True)[:, 0])
            boxes.append(jb)
        else:
            boxes.append(torch.zeros((0, 4)))
    t = torch.cat(targets) if targets else torch.zeros((0, side, side))
    return boxes, t


def mask_loss(logits: torch.Tensor, target: torch.Tensor, dice: float) -> torch.Tensor:
    """Binary cross-entropy (mean over pixels) + ``dice`` x (1 - soft Dice), averaged over instances."""
    bce = F.binary_cross_entropy_with_logits(logits, target, reduction="none").mean((1, 2))
    p = logits.sigmoid()
    d = 1.0 - (2.0 * (p * target).sum((1, 2)) + 1.0) / (p.sum((1, 2)) + target.sum((1, 2)) + 1.0)
    return (bce + dice * d).mean()


def _limit(boxes: list[torch.Tensor], targets: torch.Tensor, n: int) -> tuple[list[torch.Tensor], torch.Tensor]:
    """At most ``n`` instances over the batch: the largest boxes (a crowd photo does not swamp a batch)."""
    allb = torch.cat(boxes)
    if len(allb) <= n:
        return boxes, targets
    area = (allb[:, 2] - allb[:, 0]) * (allb[:, 3] - allb[:, 1])
    keep = torch.zeros(len(allb), dtype=torch.bool)
    keep[area.argsort(descending=True, stable=True)[:n]] = True
    out, k0 = [], 0
    for b in boxes:
        out.append(b[keep[k0:k0 + len(b)]])
        k0 += len(b)
    return out, targets[keep]


# --- model ---------------------------------------------------------------------------------------------------

def build_model(cfg: MaskTrainConfig) -> torch.nn.Module:
    """``YOLOXMasks`` with the ``init`` checkpoint's network and conf (its mask head too, when it has one) and a
    new mask head of ``cfg.mask`` otherwise (initialised from ``seed``); toy: a random network."""
    from vslam.nn.checkpoint import load_model
    from vslam.nn.registry import DETECTORS

    if cfg.toy:
        with torch.random.fork_rng():
            torch.manual_seed(cfg.seed)
            return DETECTORS.build(ARCH, {"depth": 0.33, "width": 0.125, "classes": ["person"], "input_size": cfg.img_size,
                                          "mask": dict(cfg.mask)})
    from vslam.resources import shipped_model

    path = cfg.init or shipped_model("yolox_nano_slam.pt")
    start, ck = load_model(path, DETECTORS, "train.init")
    conf = {k: v for k, v in ck["conf"].items() if k != "mask"}
    with torch.random.fork_rng():
        torch.manual_seed(cfg.seed)
        model = DETECTORS.build(ARCH, {**conf, "mask": {**ck["conf"].get("mask", {}), **dict(cfg.mask)}})
    missing, unexpected = model.load_state_dict(start.state_dict(), strict=False)
    if unexpected or any(not k.startswith("mask_head.") for k in missing):
        raise ConfigError(f"{path}: not a YOLOX detector checkpoint for the mask head (train.init)")
    return model


def _frozen(model: torch.nn.Module) -> None:
    for name, p in model.named_parameters():
        p.requires_grad_(name.startswith("mask_head."))
    model.eval()  # BatchNorm statistics stay the init's; the head has none
    model.mask_head.train()


def _save(model: torch.nn.Module, path: Path, cfg: MaskTrainConfig, **extra: Any) -> Path:
    from vslam.nn.checkpoint import save_model

    meta = {"init": cfg.init or "vslam/models/yolox_nano_slam.pt", "command": "vslam train yolox-masks",
            "train": asdict(cfg)}
    meta.update(extra.pop("meta", {}))
    return save_model(model, path, ARCH, meta=meta, **extra)


def _resume(last: Path, cfg: MaskTrainConfig, model: torch.nn.Module, opt: torch.optim.Optimizer) -> int:
    """Model and optimiser from ``last`` (weights-only) -> the iteration to continue from."""
    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    what, note = "mask head training checkpoint", "resume refused"
    ck = read_checkpoint(last, what, ("arch", "state_dict", "optimizer", "iteration", "train"), note=note)
    with reading(last, what, note):
        if _recipe(dict(ck["train"])) != _recipe(asdict(cfg)):
            raise ConfigError(f"{last}: was trained with a different config; resume needs the same one")
        load_state(model, ck["state_dict"], last, what, note)
        opt.load_state_dict(ck["optimizer"])
        return int(ck["iteration"])


def _lr(cfg: MaskTrainConfig, it: int) -> float:
    """Linear warm-up, then cosine to 5 % of ``lr``."""
    if it < cfg.warmup:
        return cfg.lr * (it + 1) / cfg.warmup
    t = (it - cfg.warmup) / max(1, cfg.iterations - cfg.warmup)
    return float(cfg.lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(t, 1.0)))))


# --- the loop ------------------------------------------------------------------------------------------------

def train(cfg: MaskTrainConfig, progress: Progress | None = None) -> dict[str, Any]:
    """Run (or resume) training -> {"loss": last logged loss, "eval": Penn-Fudan val mask IoUs or {}}."""
    from vslam.dynamic.yolox_detector import YoloxDetector
    from vslam.nn.detectors.yolox import fuse_conv_bn

    if cfg.toy:  # the toy's sizes where the caller left the defaults
        base = MaskTrainConfig()
        cfg = replace(cfg, **{k: v for k, v in TOY.items() if k != "mask" and getattr(cfg, k) == getattr(base, k)},
                      mask={**TOY["mask"], **cfg.mask})
    dev = torch.device("cuda" if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available()) else "cpu")
    if dev.type == "cpu":
        torch.set_num_threads(max(1, cfg.threads))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    model = build_model(cfg).to(dev)
    side, margin = int(model.conf["mask"]["side"]), float(model.conf["mask"]["margin"])
    _frozen(model)
    features = fuse_conv_bn(copy.deepcopy(model).eval())  # the frozen network's neck outputs, BN folded: faster
    opt = torch.optim.AdamW(model.mask_head.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = _resume(out / "last.pt", cfg, model, opt) if cfg.resume and (out / "last.pt").is_file() else 0
    if start:
        log.info("resumed at iteration %d", start)
    if cfg.toy:
        data = MaskData(toy_samples(16, cfg.img_size, np.random.default_rng(cfg.seed)), [], [], None)
    else:
        data = training_data(cfg, tuple(model.names))
    log.info("mask head: %d samples, %d backgrounds, %d cutouts", len(data.samples), len(data.backgrounds),
             len(data.cutouts))
    loss_v = float("nan")
    with open(out / "log.csv", "a") as f:
        if start == 0:
            f.write("iteration,lr,loss,instances,seconds\n")
        t0 = time.perf_counter()
        for it in range(start, cfg.iterations):
            samples = draw_batch(data, cfg, it)
            boxes, target = roi_targets(samples, cfg, side, margin, np.random.default_rng([cfg.seed, it, 1]))
            boxes, target = _limit(boxes, target, cfg.max_rois)
            for g in opt.param_groups:
                g["lr"] = _lr(cfg, it)
            if len(target):
                x = torch.from_numpy(np.stack([s.image for s in samples])).to(dev).permute(0, 3, 1, 2).float()
                with torch.no_grad():
                    feats = features({"image": x})["feats"]
                logits = model.mask_logits(feats, x, model.rois([b.to(dev) for b in boxes]))
                loss = mask_loss(logits, target.to(dev), cfg.dice)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.mask_head.parameters(), 10.0)
                opt.step()
                loss_v = float(loss.detach())
            if it % cfg.log_every == 0 or it + 1 == cfg.iterations:
                f.write(f"{it},{_lr(cfg, it):.6g},{loss_v:.5f},{len(target)},{time.perf_counter() - t0:.1f}\n")
                f.flush()
                log.info("it %d loss %.4f (%d instances)", it, loss_v, len(target))
            if (it + 1) % cfg.ckpt_every == 0 or it + 1 == cfg.iterations:
                _save(model, out / "last.pt", cfg, optimizer=opt.state_dict(), iteration=it + 1, train=asdict(cfg))
            if progress is not None:
                progress(it + 1, cfg.iterations)
    model.eval()
    metrics: dict[str, Any] = {}
    if cfg.evaluate:
        model = model.cpu()
        if cfg.pick_threshold:
            t, ious = pick_threshold(YoloxDetector(model, img_size=int(model.conf["input_size"])), cfg.penn_fudan)
            model.conf["mask"]["threshold"] = t
            metrics["threshold_train_iou"] = ious
        metrics.update(evaluate_penn_fudan(YoloxDetector(model, img_size=int(model.conf["input_size"]), conf=0.001)))
    _save(model, out / "model.pt", cfg, meta={"metrics": metrics})
    if cfg.weights:
        _save(model, cfg.weights, cfg, meta={"metrics": metrics})
    (out / "metrics.json").write_text(json.dumps({"loss": loss_v, "eval": metrics}, indent=2))
    return {"loss": loss_v, "eval": metrics}


def _prompted(det: Any, root: str, split: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per Penn-Fudan ``split`` image: (logits, regions, true masks, image shape) of its people with a true mask,
    the head prompted with their true boxes."""
    from vslam.paths import data_root
    from vslam.train.photos import load_records

    path = Path(root) if Path(root).is_absolute() else data_root() / root
    _, records = load_records(path, split)  # type: ignore[arg-type]
    out = []
    for rec in records:
        gm = rec.masks()
        if gm is None or not (rec.mask_ids > 0).any():
            continue
        has = rec.mask_ids > 0
        img = rec.image()
        logits, regions = det.prompted_logits(img, rec.boxes[has])
        out.append((logits, regions, gm[has], np.array(img.shape[:2])))
    return out


def _mean_iou(cases: list[tuple[np.ndarray, ...]], cut: float) -> tuple[float, int]:
    from vslam.dynamic.yolox_detector import paste_masks

    ious = []
    for logits, regions, gm, shape in cases:
        pm = paste_masks(logits, regions, (int(shape[0]), int(shape[1])), cut)[0]
        ious += [float((a & b).sum() / max((a | b).sum(), 1)) for a, b in zip(pm, gm)]
    return (float(np.mean(ious)) if ious else float("nan")), len(ious)


def pick_threshold(det: Any, root: str = "penn_fudan/PennFudanPed") -> tuple[float, dict[str, float]]:
    """The mask probability cut of ``THRESHOLDS`` with the best prompted mask IoU on Penn-Fudan train (never val)
    -> (threshold, {threshold: IoU})."""
    cases = _prompted(det, root, "train")
    ious = {f"{t:g}": _mean_iou(cases, float(np.log(t / (1 - t))))[0] for t in THRESHOLDS}
    best = max(THRESHOLDS, key=lambda t: ious[f"{t:g}"])
    log.info("mask threshold %g (Penn-Fudan train prompted IoU by threshold: %s)", best, ious)
    return float(best), ious


def evaluate_penn_fudan(det: Any, root: str = "penn_fudan", split: str = "val") -> dict[str, Any]:
    """Mask IoU on Penn-Fudan ``split`` people: ``prompted_mask_iou`` with the true boxes as prompts (the
    teacher's protocol), and ``vslam eval-detector``'s matched ``mask_iou/person`` etc. with the detector's own
    boxes at the SLAM score threshold."""
    from vslam.dynamic.config import DynamicConfig
    from vslam.eval.detector import evaluate, predict
    from vslam.paths import data_root
    from vslam.train.photos import load_records

    iou, n = _mean_iou(_prompted(det, root, split), det.mask_cut())
    path = Path(root) if Path(root).is_absolute() else data_root() / root
    _, records = load_records(path, split)  # type: ignore[arg-type]
    rep = evaluate(records, predict(det, records), DynamicConfig().score_threshold)
    keep = {k: v for k, v in rep.items() if k.endswith("/person") and (k.startswith(("mask_iou", "box_mask_iou", "n_masks",
                                                                                      "gt_box_mask_iou", "AP50/")))}
    keep = {k: float(v) if isinstance(v, (float, np.floating)) else int(v) for k, v in keep.items()}  # plain types:
    # the metrics go into checkpoints that are read weights-only
    return {"prompted_mask_iou/person": iou, "n_prompted": n, "threshold": float(det.model.conf["mask"]["threshold"]), **keep}
