"""``vslam train detector``: train the attention detector on COCO128 (YOLO format) + synthetic frames.

Seeded and resumable: the batch of iteration ``it`` is drawn from ``np.random.default_rng([seed, it])`` and
``last.pt`` holds model + optimiser + iteration, so an interrupted run resumed with ``resume: true`` gives the
same weights as an uninterrupted one. At the end BatchNorm statistics are recomputed exactly on training
batches ("precise BN", Wu & Johnson, "Rethinking Batch in BatchNorm", 2021: short runs leave the running
averages stale), then AP50 / AP50-95 per class is measured on held-out sets: COCO128 val2017 and synthetic
rooms of seeds never used for training. Outputs in ``out``: last.pt, model.pt (weights + config + names +
metrics), metrics.json, log.csv.

Several GPUs (or CPU processes): ``torchrun --nproc_per_node=N -m vslam.cli train detector ...``. Each rank
draws its own batch (``default_rng([seed, it, rank])``: the global batch is N x ``batch``), gradients are
averaged by DistributedDataParallel (NCCL on CUDA, gloo on CPU), and rank 0 alone writes logs, checkpoints
and the final model. Without torchrun (WORLD_SIZE unset) nothing changes: single-GPU and CPU runs give the
weights they gave before.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from vslam import ddp
from vslam.dynamic.data import Sample, collate, load_yolo, place, synthetic_samples
from vslam.dynamic.detector import postprocess, save_checkpoint
from vslam.dynamic.loss import detection_loss
from vslam.dynamic.metrics import detection_report
from vslam.dynamic.model import DetectorConfig, YoloDetector, decode, recalibrate_bn
from vslam.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    out: str = "runs/train_detector"
    classes: tuple[str, ...] = ("person", "bicycle", "car", "chair")
    coco: str = "coco128"  # YOLO-format folder, relative to $VSLAM_DATA or absolute; "" to leave out
    synthetic_seeds: tuple[int, ...] = (101, 102, 103, 104)  # training rooms
    synthetic_val_seeds: tuple[int, ...] = (201,)  # held-out rooms
    synthetic_frames: int = 300
    synthetic_stride: int = 6
    synthetic_movers: int = 6
    synthetic_size: tuple[int, int] = (640, 480)  # width, height of the rendered frames
    img_size: int = 320  # square training canvas, multiple of 32
    batch: int = 8
    iterations: int = 3000
    lr: float = 2e-3
    weight_decay: float = 5e-4
    warmup: int = 100
    attention: str = "esea"  # none | se | cbam | esea
    scale: str = "n"
    width: float | None = None  # overrides the scale's width multiple
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
    threads: int = 0  # torch CPU threads, 0: torch's default
    ckpt_every: int = 100
    log_every: int = 10
    bn_batches: int = 16
    resume: bool = False
    toy: bool = False  # tiny model, tiny images, a few iterations: a smoke test of the whole recipe on CPU

    def __post_init__(self) -> None:
        if self.img_size % 32:
            raise ConfigError(f"train.img_size must be a multiple of 32, got {self.img_size}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device must be auto, cpu or cuda, got {self.device!r}")


TOY = dict(img_size=64, batch=4, iterations=20, width=0.125, coco="", synthetic_seeds=(101,), synthetic_val_seeds=(201,),
           synthetic_frames=24, synthetic_stride=4, synthetic_size=(160, 120), ckpt_every=10, bn_batches=2)


def resolve(cfg: TrainConfig) -> TrainConfig:
    return replace(cfg, **{k: v for k, v in TOY.items()}, toy=True) if cfg.toy else cfg


def build_data(cfg: TrainConfig) -> tuple[list[Sample], dict[str, list[Sample]]]:
    """Training samples and named held-out sets."""
    from vslam.paths import data_root

    person = cfg.classes.index("person") if "person" in cfg.classes else None
    train, val = [], {}
    if cfg.coco:
        root = Path(cfg.coco) if Path(cfg.coco).is_absolute() else data_root() / cfg.coco
        train += load_yolo(root, "train2017", cfg.classes)
        val["coco128-val"] = load_yolo(root, "val2017", cfg.classes)
    if person is not None and cfg.synthetic_seeds:
        w, h = cfg.synthetic_size
        kw = dict(n_frames=cfg.synthetic_frames, stride=cfg.synthetic_stride, person=person, n_movers=cfg.synthetic_movers, width=w, height=h)
        train += synthetic_samples(cfg.synthetic_seeds, **kw)
        if cfg.synthetic_val_seeds:
            val["synthetic-val"] = synthetic_samples(cfg.synthetic_val_seeds, **kw)
    if not train:
        raise ConfigError("train: no training data (set coco and/or synthetic_seeds)")
    return train, val


def _batch(data: list[Sample], cfg: TrainConfig, it: int, dev: torch.device, rank: int | None = None) -> tuple[torch.Tensor, ...]:
    rng = np.random.default_rng([cfg.seed, it] if rank is None else [cfg.seed, it, rank])
    samples = [place(data[i], cfg.img_size, rng) for i in rng.integers(0, len(data), cfg.batch)]
    return tuple(torch.from_numpy(a).to(dev) for a in collate(samples))


def _recipe(d: dict) -> dict:
    """The config fields that change the trained weights (resume must match them)."""
    return {k: v for k, v in d.items() if k not in ("resume", "threads", "device", "ckpt_every", "log_every")}


def _lr(cfg: TrainConfig, it: int) -> float:
    if it < cfg.warmup:
        return cfg.lr * (it + 1) / cfg.warmup
    t = (it - cfg.warmup) / max(1, cfg.iterations - cfg.warmup)
    return cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))


@torch.no_grad()
def evaluate(model: YoloDetector, data: list[Sample], cfg: TrainConfig, dev: torch.device) -> dict[str, float]:
    """AP per class on ``data`` letterboxed to ``img_size`` (no augmentation); also ms per image."""
    model.eval()
    dets, gts = [], []
    t0 = time.perf_counter()
    for k in range(0, len(data), 16):
        placed = [place(s, cfg.img_size, None) for s in data[k:k + 16]]
        x = torch.from_numpy(collate(placed)[0]).to(dev)
        boxes, probs = decode(model, model(x))
        for (b, s, c), p in zip(postprocess(boxes, probs, conf=0.001, iou=0.6), placed):
            dets.append((b.cpu().numpy(), s.cpu().numpy(), c.cpu().numpy()))
            gts.append((p.boxes, p.labels))
    rep = detection_report(dets, gts, list(cfg.classes))
    rep["ms_per_image"] = (time.perf_counter() - t0) * 1e3 / max(1, len(data))
    return rep


def train(cfg: TrainConfig) -> dict[str, dict[str, float]]:
    """Run (or resume) training; returns the held-out metrics per set ({} on ranks other than 0)."""
    cfg = resolve(cfg)
    dev = torch.device("cuda" if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available()) else "cpu")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    return ddp.launch(dev, functools.partial(_train, cfg))


def _train(cfg: TrainConfig, dev: torch.device, rank: int, n_ranks: int) -> dict[str, dict[str, float]]:
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)  # weight initialisation
    model = YoloDetector(DetectorConfig(cfg.scale, cfg.attention, len(cfg.classes), width=cfg.width)).to(dev)
    net = ddp.wrap(model, dev, n_ranks)  # what the forward pass goes through
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    if cfg.resume and (out / "last.pt").is_file():
        ck = torch.load(out / "last.pt", map_location=dev, weights_only=False)
        if _recipe(ck["train"]) != _recipe(asdict(cfg)):
            raise ConfigError(f"{out / 'last.pt'}: was trained with a different config; resume needs the same one")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start = int(ck["iteration"])
        log.info("resumed at iteration %d", start)
    train_set, val_sets = build_data(cfg)
    log.info("training samples: %d; held-out: %s", len(train_set), {k: len(v) for k, v in val_sets.items()})
    model.train()
    lead = rank == 0  # the one rank that writes
    with open(out / "log.csv", "a") if lead else contextlib.nullcontext() as f:
        if start == 0 and lead:
            f.write("iteration,lr,loss,box,cls,dfl,seconds\n")
        t0 = time.perf_counter()
        for it in range(start, cfg.iterations):
            x, gb, gl, gm = _batch(train_set, cfg, it, dev, rank if n_ranks > 1 else None)
            for g in opt.param_groups:
                g["lr"] = _lr(cfg, it)
            loss, parts = detection_loss(model, net(x), gb, gl, gm)
            opt.zero_grad(set_to_none=True)
            loss.backward()  # DDP: gradients averaged over the ranks here
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            if not lead:
                continue
            if it % cfg.log_every == 0 or it + 1 == cfg.iterations:
                f.write(f"{it},{_lr(cfg, it):.6g},{float(loss.detach()):.5f},{parts['box']:.5f},{parts['cls']:.5f},"
                        f"{parts['dfl']:.5f},{time.perf_counter() - t0:.1f}\n")
                f.flush()
                log.info("it %d loss %.4f %s", it, float(loss.detach()), parts)
            if (it + 1) % cfg.ckpt_every == 0 or it + 1 == cfg.iterations:
                save_checkpoint(out / "last.pt", model, list(cfg.classes), optimizer=opt.state_dict(),
                                iteration=it + 1, train=asdict(cfg))
    if n_ranks > 1:
        ddp.check_in_sync(model)
    if not lead:
        return {}
    recalibrate_bn(model, [_batch(train_set, cfg, 10_000_000 + k, dev)[0] for k in range(cfg.bn_batches)])
    metrics = {name: evaluate(model, data, cfg, dev) for name, data in val_sets.items()}
    save_checkpoint(out / "model.pt", model, list(cfg.classes), img_size=cfg.img_size, metrics=metrics, train=asdict(cfg))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
