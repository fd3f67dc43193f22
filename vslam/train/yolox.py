"""``vslam train yolox``: fine-tune the YOLOX-style detector (``vslam.nn.detectors.yolox``) from the converted
public weights on our data (``vslam.train.yolox_data``), on the CPU.

Why: COCO-trained, the network boxes the TUM teddy scene's big plush bear in its yellow shirt as a person and
SLAM masks the scene's main texture; composites of pasted people over our indoor frames, where the only people
are the pasted ones, teach it that such objects are not people, while Penn-Fudan, KITTI object and COCO128
train keep what it knows of real people and vehicles.

Recipe (YOLOX, Ge et al. 2021, with the small-batch changes fine-tuning on 2 CPU cores needs): the SimOTA loss
(``yolox_loss``, KITTI DontCare left out of objectness); BatchNorm in eval mode (``freeze_bn``: batches of 8 would
replace the statistics the converter wrote by noisy batch statistics); the backbone frozen by default (the head
and neck learn what is a person here; half the backward pass); AdamW (or SGD with Nesterov momentum), linear
warmup, cosine decay; gradients clipped; an exponential moving average of the weights (Megvii's ModelEMA, decay
ramped by 1 - exp(-updates / ``ema_tau``)) is what is saved.

Seeded and resumable: the batch of iteration ``it`` depends on (seed, it) alone (``yolox_data.draw_batch``) and
``OUT/last.pt`` holds weights, EMA, optimiser and iteration, read back weights-only; a resumed run ends with the
weights of an uninterrupted one. Outputs in ``out``: last.pt, model.pt (``vslam.nn.checkpoint.save_model``, the
format ``YoloxDetector`` loads), log.csv, config.json, metrics.json.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from vslam.errors import ConfigError
from vslam.progress import Progress
from vslam.train.yolox_data import Batch, YoloxData, YoloxDataConfig, draw_batch, load_sources

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class YoloxTrainConfig:
    out: str = "runs/train_yolox"
    init: str = ""  # checkpoint to start from ({arch, conf, state_dict, meta}); "" = vslam/models/yolox_nano_slam.pt
    data: YoloxDataConfig = field(default_factory=YoloxDataConfig)
    pseudo: bool = True  # the starting network's boxes where Penn-Fudan leaves people and cars unlabelled
    pseudo_threshold: float = 0.5
    batch: int = 8  # square batches (KITTI batches: data.wide_batch)
    iterations: int = 1000
    optimizer: str = "adamw"  # adamw | sgd (Nesterov momentum 0.9)
    lr: float = 1e-4
    weight_decay: float = 5e-4  # convolution weights only
    warmup: int = 50
    clip: float = 10.0  # gradient norm
    freeze_backbone: bool = True
    # only the parameters whose names start with one of these train (empty: all but a frozen backbone).
    # [head.cls_convs, head.cls_preds, head.obj_preds] keeps the source's boxes (the COCO box precision, AP75,
    # that a stage of the whole neck and head lost) while class and objectness learn
    train_only: tuple[str, ...] = ()
    # > 0: weight of a loss that keeps the trained network's boxes at the starting network's (frozen) wherever
    # the start boxes a thing (its score >= box_distill_min_score): 1 - IoU of the two boxes, averaged over
    # those anchors. Class and objectness learn freely; the box precision the start learned on COCO is what a
    # stage without it lost (COCO128 val AP75, models/README.md)
    box_distill: float = 0.0
    box_distill_min_score: float = 0.05
    ema_decay: float = 0.995
    ema_tau: float = 100.0
    seed: int = 0
    threads: int = 2  # torch CPU threads (the machine is shared: at most 2)
    ckpt_every: int = 25
    log_every: int = 10
    weights: str = ""  # also write the final model here (the shipped copy under vslam/models/)
    # stop after this many minutes of training in this session (0: no limit): last.pt and a model.pt of the EMA
    # weights so far are written, and ``resume`` continues the same schedule later
    max_minutes: float = 0.0
    resume: bool = False
    device: str = "cpu"  # cpu (the recipe is sized for it) | cuda | auto
    toy: bool = False  # tiny canvases, a few iterations, few samples: a smoke test of the whole recipe

    def __post_init__(self) -> None:
        if self.optimizer not in ("sgd", "adamw"):
            raise ConfigError(f"train.optimizer must be sgd or adamw, got {self.optimizer!r}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device must be auto, cpu or cuda, got {self.device!r}")
        if not 1 <= self.threads <= 2:
            raise ConfigError(f"train.threads: 1 or 2 (the CPU is shared), got {self.threads}")
        if self.box_distill < 0 or not 0 <= self.box_distill_min_score < 1:
            raise ConfigError(f"train: box_distill must be >= 0 and box_distill_min_score in [0, 1), got "
                              f"{self.box_distill} and {self.box_distill_min_score}")
        if self.batch < 1 or self.iterations < 1 or self.lr <= 0 or not 0 <= self.ema_decay < 1:
            raise ConfigError("train: batch, iterations and lr must be positive and ema_decay in [0, 1)")


TOY = dict(batch=2, iterations=6, warmup=2, ckpt_every=3, log_every=1, pseudo=False)
TOY_DATA = dict(fit=(96, 96), canvas=(64, 64), wide_fit=(192, 64), wide_canvas=(128, 64), wide_every=3, wide_batch=2)


def resolve(cfg: YoloxTrainConfig) -> YoloxTrainConfig:
    if not cfg.toy:
        return cfg
    return replace(cfg, **TOY, data=replace(cfg.data, **TOY_DATA))


def _init_path(cfg: YoloxTrainConfig) -> Path:
    from vslam.resources import shipped_model

    return Path(cfg.init) if cfg.init else shipped_model("yolox_nano_slam.pt")


def load_start(cfg: YoloxTrainConfig) -> tuple[torch.nn.Module, dict]:
    """The network to fine-tune, from ``init`` -> (model, the file's dict)."""
    from vslam.nn.checkpoint import load_model
    from vslam.nn.detectors.yolox import YOLOX
    from vslam.nn.registry import DETECTORS

    model, ck = load_model(_init_path(cfg), DETECTORS, "train.init")
    if not isinstance(model, YOLOX):
        raise ConfigError(f"{_init_path(cfg)}: train yolox fine-tunes a YOLOX-style network, not {ck['arch']!r}")
    return model, ck


class ModelTeacher:
    """The starting network as a pseudo-label teacher (``pseudo.Teacher``): keyed by its file's SHA-1."""

    def __init__(self, model: torch.nn.Module, path: Path, threshold: float, img_size: int):
        from vslam.dynamic.yolox_detector import YoloxDetector

        self.fingerprint = f"yolox-{img_size}-" + hashlib.sha1(path.read_bytes()).hexdigest()
        self._det = YoloxDetector(model, img_size=img_size, conf=threshold)

    def detect(self, image: np.ndarray):
        return self._det.detect(image)


def training_data(cfg: YoloxTrainConfig, model: torch.nn.Module) -> YoloxData:
    teacher = ModelTeacher(model, _init_path(cfg), cfg.pseudo_threshold, cfg.data.fit[0]) if cfg.pseudo else None
    data = load_sources(cfg.data, tuple(model.names), teacher, str(Path(cfg.out) / "pseudo_cache"),
                        cfg.pseudo_threshold)
    if cfg.toy:  # a few samples of each kind
        data = YoloxData({k: v[:4] for k, v in data.sources.items()}, data.wide[:2], data.backgrounds[:4],
                         data.cutouts[:4])
    return data


class Ema:
    """Exponential moving average of a model's floating-point state (Megvii's ModelEMA): after the n-th update
    ema = d ema + (1 - d) w with d = decay (1 - exp(-n / tau)), so early updates follow the weights closely."""

    def __init__(self, model: torch.nn.Module, decay: float, tau: float):
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)
        self.decay, self.tau, self.updates = decay, tau, 0

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        src = model.state_dict()
        for k, v in self.model.state_dict().items():
            if v.is_floating_point():
                v.mul_(d).add_(src[k].detach(), alpha=1 - d)
            else:
                v.copy_(src[k])


def _lr(cfg: YoloxTrainConfig, it: int) -> float:
    if it < cfg.warmup:
        return cfg.lr * (it + 1) / cfg.warmup
    t = (it - cfg.warmup) / max(1, cfg.iterations - cfg.warmup)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))


def _optimizer(cfg: YoloxTrainConfig, model: torch.nn.Module) -> torch.optim.Optimizer:
    train = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    decay = [p for n, p in train if p.ndim > 1]  # convolution weights; BN affine and biases without decay
    rest = [p for n, p in train if p.ndim <= 1]
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": rest, "weight_decay": 0.0}]
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(groups, lr=cfg.lr)
    return torch.optim.SGD(groups, lr=cfg.lr, momentum=0.9, nesterov=True)


def _train_mode(model: torch.nn.Module, cfg: YoloxTrainConfig) -> None:
    from vslam.nn.detectors.yolox_loss import freeze_bn

    model.train()
    freeze_bn(model)
    if cfg.freeze_backbone:
        model.neck.backbone.eval()
        for p in model.neck.backbone.parameters():
            p.requires_grad_(False)
    if cfg.train_only:
        names = [n for n, _ in model.named_parameters()]
        unknown = [pre for pre in cfg.train_only if not any(n.startswith(pre) for n in names)]
        if unknown:
            raise ConfigError(f"train.train_only: no parameter of the network starts with {', '.join(unknown)} "
                              f"(names look like {names[-1]})")
        for n, p in model.named_parameters():
            if not n.startswith(tuple(cfg.train_only)):
                p.requires_grad_(False)


def batch_loss(model: torch.nn.Module, batch: Batch, dev: torch.device, teacher: torch.nn.Module | None = None,
               distill: float = 0.0, min_score: float = 0.05) -> dict[str, torch.Tensor]:
    """The YOLOX loss of ``model`` on ``batch`` (images BGR 0..255 as the network runs); with ``teacher`` also
    ``distill`` x the box-distillation term ("distill", ``YoloxTrainConfig.box_distill``)."""
    from vslam.nn.detectors.yolox_loss import yolox_loss

    x = torch.from_numpy(batch.images).to(dev).float()
    targets = [(torch.from_numpy(b).to(dev), torch.from_numpy(c).to(dev)) for b, c in zip(batch.boxes, batch.labels)]
    ignore = [torch.from_numpy(g).to(dev) for g in batch.ignore]
    out = model({"image": x})
    loss = yolox_loss(out, targets, tuple(x.shape[2:]), ignore=ignore)
    if teacher is not None and distill > 0:
        with torch.no_grad():
            ref = teacher({"image": x})
        term = box_distill_loss(out, ref, min_score)
        loss["loss"] = loss["loss"] + distill * term
        loss["distill"] = term.detach()
    return loss


def box_distill_loss(out: dict[str, torch.Tensor], ref: dict[str, torch.Tensor],
                     min_score: float = 0.05) -> torch.Tensor:
    """Mean 1 - IoU between ``out``'s and ``ref``'s boxes over the anchors where ``ref`` scores a class at
    ``min_score`` or more (objectness x best class, as at inference); 0 where it scores none."""
    from vslam.nn.ops import box_iou_paired

    with torch.no_grad():
        logits = ref["logits"]
        score = torch.sigmoid(logits[..., 4]) * torch.sigmoid(logits[..., 5:]).max(-1).values
        sel = score >= min_score
    if not sel.any():
        return out["boxes"].sum() * 0.0
    return (1.0 - box_iou_paired(out["boxes"][sel], ref["boxes"][sel].detach())).mean()


def _recipe(d: dict) -> dict:
    """The config fields that change the trained weights (resume must match them)."""
    return {k: v for k, v in d.items()
            if k not in ("resume", "threads", "device", "ckpt_every", "log_every", "weights", "max_minutes")}


def _save_last(path: Path, model: torch.nn.Module, ema: Ema, opt: torch.optim.Optimizer, it: int,
               cfg: YoloxTrainConfig) -> None:
    tmp = path.with_suffix(".pt.tmp")
    torch.save({"model": model.state_dict(), "ema": ema.model.state_dict(), "ema_updates": ema.updates,
                "optimizer": opt.state_dict(), "iteration": it, "train": asdict(cfg)}, tmp)
    tmp.replace(path)  # atomic: an interrupted save leaves the previous checkpoint


def _resume(path: Path, cfg: YoloxTrainConfig, model: torch.nn.Module, ema: Ema, opt: torch.optim.Optimizer,
            dev: torch.device) -> int:
    """State from ``path`` (weights-only: a file planted in the output folder never runs code) -> iteration."""
    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    what, note = "YOLOX training checkpoint", "resume refused"
    ck = read_checkpoint(path, what, ("model", "ema", "ema_updates", "optimizer", "iteration", "train"),
                         map_location=dev, note=note)
    with reading(path, what, note):
        if _recipe(json.loads(json.dumps(ck["train"]))) != _recipe(json.loads(json.dumps(asdict(cfg)))):
            raise ConfigError(f"{path}: was trained with a different config; resume needs the same one")
        load_state(model, ck["model"], path, what, note)
        load_state(ema.model, ck["ema"], path, what, note)
        ema.updates = int(ck["ema_updates"])
        opt.load_state_dict(ck["optimizer"])
        return int(ck["iteration"])


def _device(cfg: YoloxTrainConfig) -> torch.device:
    cuda = cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available())
    return torch.device("cuda" if cuda else "cpu")


def train(cfg: YoloxTrainConfig, progress: Progress | None = None, data: YoloxData | None = None) -> dict:
    """Run (or resume) fine-tuning -> metrics (final loss terms, seconds). ``data``: the samples to draw from
    (default ``training_data(cfg)``; tests pass synthetic ones). ``progress(done, total)`` after each step."""
    cfg = resolve(cfg)
    torch.set_num_threads(cfg.threads)
    dev = _device(cfg)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    model, ck = load_start(cfg)
    model.to(dev)
    if data is None:
        data = training_data(cfg, model)
    # the start, frozen, for the box-distillation term (loaded before training moves a tensor)
    teacher = copy.deepcopy(model).eval().requires_grad_(False) if cfg.box_distill > 0 else None
    _train_mode(model, cfg)
    ema = Ema(model, cfg.ema_decay, cfg.ema_tau)
    opt = _optimizer(cfg, model)
    start = 0
    if cfg.resume and (out / "last.pt").is_file():
        start = _resume(out / "last.pt", cfg, model, ema, opt, dev)
        log.info("resumed at iteration %d", start)
    (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
    person = list(model.names).index("person")
    log.info("training samples: %s, wide %d, %d backgrounds x %d cutouts", {k: len(v) for k, v in data.sources.items()},
             len(data.wide), len(data.backgrounds), len(data.cutouts))
    params = [p for p in model.parameters() if p.requires_grad]
    parts: dict[str, float] = {}
    t0, done = time.perf_counter(), start
    with open(out / "log.csv", "a") as f:
        if start == 0:
            f.write("iteration,lr,wide,loss,box,obj,cls,fg,seconds\n")
        for it in range(start, cfg.iterations):
            batch = draw_batch(data, cfg.data, cfg.seed, it, cfg.batch, person)
            for g in opt.param_groups:
                g["lr"] = _lr(cfg, it)
            loss = batch_loss(model, batch, dev, teacher, cfg.box_distill, cfg.box_distill_min_score)
            opt.zero_grad(set_to_none=True)
            loss["loss"].backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.clip)
            opt.step()
            ema.update(model)
            done = it + 1
            parts = {k: float(v.detach()) for k, v in loss.items()}
            if progress is not None:
                progress(it + 1, cfg.iterations)
            if it % cfg.log_every == 0 or it + 1 == cfg.iterations:
                f.write(f"{it},{_lr(cfg, it):.6g},{int(batch.wide)},{parts['loss']:.5f},{parts['box']:.5f},"
                        f"{parts['obj']:.5f},{parts['cls']:.5f},{int(parts['fg'])},{time.perf_counter() - t0:.1f}\n")
                f.flush()
            over = cfg.max_minutes > 0 and time.perf_counter() - t0 > 60 * cfg.max_minutes
            if (it + 1) % cfg.ckpt_every == 0 or it + 1 == cfg.iterations or over:
                _save_last(out / "last.pt", model, ema, opt, it + 1, cfg)
            if over:
                log.warning("max_minutes reached: stopped after iteration %d of %d", it + 1, cfg.iterations)
                break
    metrics = {"iterations": cfg.iterations, "done": done, "seconds_this_session": round(time.perf_counter() - t0, 1),
               "last_loss": parts}
    save_final(ema.model, cfg, ck, metrics)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def save_final(model: torch.nn.Module, cfg: YoloxTrainConfig, start: dict, metrics: dict) -> None:
    """``model`` (the EMA weights) through ``save_model`` at OUT/model.pt (and ``weights``): the starting file's
    arch and conf, its meta under ``start`` with this run's recipe."""
    from vslam.nn.checkpoint import save_model

    meta = {"start": {k: start["meta"].get(k) for k in ("source", "licence", "command", "classes")},
            "init": str(_init_path(cfg)), "train": asdict(cfg), "metrics": metrics,
            "licence": start["meta"].get("licence", ""), "classes": list(model.names)}
    for path in [Path(cfg.out) / "model.pt"] + ([Path(cfg.weights)] if cfg.weights else []):
        save_model(model, path, start["arch"], meta)
