"""``vslam train detector``: train the attention detector on COCO128 (YOLO format) + synthetic frames, with
copy-paste of COCO people onto the training frames of the real sequences (``copy_paste``, ``vslam.train.copy_paste``).
The COCO images whose people walk through the dynamic benchmark are never trained on (``held_out_people``).

Seeded and resumable: the batch of iteration ``it`` is drawn from ``np.random.default_rng([seed, it])`` and
``last.pt`` holds model + optimiser + iteration, so an interrupted run resumed with ``resume: true`` gives the
same weights as an uninterrupted one. At the end BatchNorm statistics are recomputed exactly on training
batches ("precise BN", Wu & Johnson, "Rethinking Batch in BatchNorm", 2021: short runs leave the running
averages stale), then AP50 / AP50-95 per class is measured on held-out sets: COCO128 val2017, the dynamic
benchmark's composited TUM frames after the training split (``eval_composite``) and synthetic rooms of seeds
never used for training. Outputs in ``out``: last.pt, model.pt (weights + config + names +
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
import itertools
import json
import logging
import math
import time
from collections import deque
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from vslam import ddp
from vslam.dynamic.detector import postprocess, save_checkpoint
from vslam.dynamic.model import DetectorConfig, YoloDetector, decode, mask_head_modules, recalibrate_bn
from vslam.errors import ConfigError
from vslam.eval.detection_metrics import detection_report
from vslam.progress import Progress
from vslam.train.detector_data import (
    Sample,
    collate,
    collate_ignore,
    collate_masks,
    collate_u8,
    load_yolo,
    place,
    synthetic_samples,
)
from vslam.train.detector_loss import LossConfig, MaskTargets, detection_loss

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
    workers: int = 0  # processes drawing batches ahead of the training step (a GPU outruns one); same weights
    ckpt_every: int = 100
    log_every: int = 10
    bn_batches: int = 16
    copy_paste: float = 0.0  # probability that a training sample is a background with pasted COCO people
    paste_people: tuple[int, int] = (1, 4)  # people per pasted sample (inclusive range)
    paste_closeup: float = 0.0  # probability that a pasted person is 1-2 image heights tall, cut by the frame
    paste_tilt: float = 0.0  # probability that a pasted person leans (rotated by up to 25 degrees)
    paste_occluded: float = 0.0  # probability that 30-70 % of a pasted person is hidden behind a patch of the scene
    # what people are pasted onto: COCO train images (their labels kept) and training frames of the sequences;
    # "kitti" is offered but off by default: its frames hold unlabelled cars and cyclists (negatives they are not)
    backgrounds: tuple[str, ...] = ("coco", "tum", "euroc")
    grey: float = 0.0  # probability of a grey training sample (EuRoC / KITTI grey cameras)
    held_out_people: bool = True  # never train on the COCO images whose people walk through the benchmark
    eval_composite: str = ""  # TUM sequence: evaluate on its frames with the benchmark's walkers composited
    eval_composite_from: int = 100  # ... from this frame on (the frames before are copy-paste backgrounds)
    weights: str = ""  # also write the final model here in float16 (the committed copy under models/)
    init: str = ""  # start from this checkpoint's weights (a further training round) instead of random ones
    masks: int = 0  # prototypes of the instance-mask head (YOLOv8-seg: 32); 0 = boxes only
    mask_gain: float = 7.5  # weight of the mask term in the loss
    # train the mask head alone over the frozen ``init`` detector (its boxes, scores and BatchNorm statistics stay
    # exactly as they were): a mask head for a trained detector at a fraction of a full run's cost
    freeze_detector: bool = False
    # real photos beside COCO128 (relative to $VSLAM_DATA or absolute; "" to leave out), their train splits only
    # (``datasets.split_of``): Penn-Fudan people with instance masks, KITTI object boxes with DontCare ignored
    penn_fudan: str = ""
    kitti_object: str = ""
    cutouts: tuple[str, ...] = ("coco",)  # where pasted people come from: coco, penn_fudan (train split)
    # sources whose unlabelled people / vehicles get the teacher's boxes (FastestDet, ``vslam.train.pseudo``):
    # coco, penn_fudan, kitti_object; the boxes train detection only (no mask)
    pseudo: tuple[str, ...] = ()
    pseudo_threshold: float = 0.5
    resume: bool = False
    evaluate: bool = True  # measure the held-out sets at the end (off where their data is not at hand)
    toy: bool = False  # tiny model, tiny images, a few iterations: a smoke test of the whole recipe on CPU

    def __post_init__(self) -> None:
        if self.img_size % 32:
            raise ConfigError(f"train.img_size must be a multiple of 32, got {self.img_size}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device must be auto, cpu or cuda, got {self.device!r}")
        for name in ("copy_paste", "paste_closeup", "paste_tilt", "paste_occluded"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"train.{name} is a probability (0-1), got {getattr(self, name)}")
        if self.masks < 0 or self.mask_gain < 0:
            raise ConfigError(f"train.masks and train.mask_gain must be >= 0, got {self.masks} and {self.mask_gain}")
        unknown = (set(self.cutouts) - {"coco", "penn_fudan"}) | (set(self.pseudo) - {"coco", "penn_fudan", "kitti_object"})
        if unknown:
            raise ConfigError(f"train.cutouts / train.pseudo: unknown source(s) {sorted(unknown)} (cutouts: coco, penn_fudan; "
                              "pseudo: coco, penn_fudan, kitti_object)")
        if self.freeze_detector and not (self.masks and self.init):
            raise ConfigError("train.freeze_detector trains a mask head over a trained detector: it needs train.masks > 0 "
                              "and train.init")


TOY = dict(img_size=64, batch=4, iterations=20, width=0.125, coco="", synthetic_seeds=(101,), synthetic_val_seeds=(201,),
           synthetic_frames=24, synthetic_stride=4, synthetic_size=(160, 120), ckpt_every=10, bn_batches=2)


def resolve(cfg: TrainConfig) -> TrainConfig:
    return replace(cfg, **{k: v for k, v in TOY.items()}, toy=True) if cfg.toy else cfg


@dataclass
class TrainData:
    """What batches are drawn from: labelled samples, and for copy-paste the backgrounds (labelled COCO samples or
    unlabelled real frames) and the person cutouts (BGRA)."""

    samples: list[Sample]
    backgrounds: list[Sample]
    cutouts: list[np.ndarray]


def _under_data(path: str) -> Path:
    from vslam.paths import data_root

    return Path(path) if Path(path).is_absolute() else data_root() / path


def _coco_root(cfg: TrainConfig) -> Path:
    return _under_data(cfg.coco)


def _held_out_stems(cfg: TrainConfig) -> frozenset[str]:
    if not (cfg.held_out_people and (cfg.copy_paste > 0 or cfg.eval_composite)):
        return frozenset()  # the recipe before copy-paste trained on every COCO128 train image
    from vslam.data.composite import benchmark_stems

    return benchmark_stems(_coco_root(cfg))


def _synthetic_kw(cfg: TrainConfig, person: int) -> dict:
    w, h = cfg.synthetic_size
    return dict(n_frames=cfg.synthetic_frames, stride=cfg.synthetic_stride, person=person, n_movers=cfg.synthetic_movers,
                width=w, height=h)


def training_data(cfg: TrainConfig) -> TrainData:
    from vslam.paths import data_root

    person = cfg.classes.index("person") if "person" in cfg.classes else None
    masks = cfg.masks > 0  # box-only recipes read no masks: their samples, draws and weights stay as they were
    sources: dict[str, list[Sample]] = {}
    backgrounds: list[Sample] = []
    cutouts: list[np.ndarray] = []
    paste = cfg.copy_paste > 0 and person is not None
    if cfg.coco:
        skip = _held_out_stems(cfg)
        sources["coco"] = load_yolo(_coco_root(cfg), "train2017", cfg.classes, skip=skip, segments=masks)
        if paste and "coco" in cfg.cutouts:
            from vslam.data.composite import person_instances

            found = person_instances(_coco_root(cfg), min_height_px=48, min_aspect=0.0, whole=False, exclude=skip)
            cutouts += [c for _, c in found]
    if cfg.penn_fudan:
        from vslam.train.photos import penn_fudan_cutouts, penn_fudan_samples

        sources["penn_fudan"] = penn_fudan_samples(_under_data(cfg.penn_fudan), cfg.classes, "train")
        if paste and "penn_fudan" in cfg.cutouts:
            cutouts += penn_fudan_cutouts(_under_data(cfg.penn_fudan))
    if cfg.kitti_object:
        from vslam.train.photos import kitti_object_samples

        sources["kitti_object"] = kitti_object_samples(_under_data(cfg.kitti_object), cfg.classes, "train")
    if cfg.pseudo:
        from vslam.train.pseudo import PseudoConfig, pseudo_label_sources, pseudo_report

        missing = [n for n in cfg.pseudo if n not in sources]
        if missing:
            raise ConfigError(f"train.pseudo names {missing}, which this recipe does not read (set train.coco / "
                              "penn_fudan / kitti_object)")
        labelled, stats = pseudo_label_sources({n: sources[n] for n in cfg.pseudo}, cfg.classes,
                                               PseudoConfig(threshold=cfg.pseudo_threshold,
                                                            cache=str(Path(cfg.out).parent / "pseudo_cache")))
        sources.update(labelled)
        log.info("teacher boxes added:\n%s", pseudo_report(stats))
    if paste and "coco" in cfg.backgrounds and "coco" in sources:
        backgrounds += sources["coco"]
    train: list[Sample] = [s for v in sources.values() for s in v]
    if paste:
        from vslam.train.copy_paste import background_files, read_background
        from vslam.train.keypoints import KeypointTrainConfig

        k = KeypointTrainConfig()  # the project's train / held-out splits of the real sequences
        src = {"tum": (k.tum, k.tum_split, k.frame_stride), "kitti": (k.kitti, k.kitti_split, k.frame_stride),
               "euroc": (k.euroc, k.euroc_split, k.frame_stride)}
        files = background_files(data_root(), {n: v for n, v in src.items() if n in cfg.backgrounds})
        imgs = [im for im in (read_background(f) for f in files) if im is not None]
        backgrounds += [Sample(im, np.zeros((0, 4)), np.zeros(0, np.int64)) for im in imgs]
        if not cutouts or not backgrounds:
            raise ConfigError("train.copy_paste needs people to paste (train.cutouts: COCO polygons, Penn-Fudan masks) "
                              "and backgrounds")
    if person is not None and cfg.synthetic_seeds:
        train += synthetic_samples(cfg.synthetic_seeds, **_synthetic_kw(cfg, person), masks=masks)
    if not train:
        raise ConfigError("train: no training data (set coco and/or synthetic_seeds)")
    return TrainData(train, backgrounds, cutouts)


def held_out_sets(cfg: TrainConfig) -> dict[str, list[Sample]]:
    """Named evaluation sets, none of them trained on: COCO128 val2017, the dynamic benchmark's composited TUM
    frames (``eval_composite``), synthetic rooms of other seeds."""
    person = cfg.classes.index("person") if "person" in cfg.classes else None
    val: dict[str, list[Sample]] = {}
    if cfg.coco:
        val["coco128-val"] = load_yolo(_coco_root(cfg), "val2017", cfg.classes)
    if cfg.eval_composite and person is not None:
        val["tum-people"] = composite_samples(cfg, person)
    if person is not None and cfg.synthetic_seeds and cfg.synthetic_val_seeds:
        val["synthetic-val"] = synthetic_samples(cfg.synthetic_val_seeds, **_synthetic_kw(cfg, person))
    return val


def composite_samples(cfg: TrainConfig, person: int) -> list[Sample]:
    """The dynamic benchmark's frames (``configs/bench.yaml``: 3 walkers, seed 0) from ``eval_composite_from``
    on, with the boxes of the visible walkers: the held-out test of what SLAM will see."""
    from vslam.data.composite import MakeDynamicConfig, composited_frames
    from vslam.paths import data_root

    seq = Path(cfg.eval_composite) if Path(cfg.eval_composite).is_absolute() else data_root() / cfg.eval_composite
    out = []
    frames = composited_frames(seq, _coco_root(cfg), MakeDynamicConfig(n_people=3, seed=0), start=cfg.eval_composite_from)
    for _, img, _, _, boxes in frames:
        b = boxes[((boxes[:, 2] - boxes[:, 0]) > 4) & ((boxes[:, 3] - boxes[:, 1]) > 4)]
        out.append(Sample(img, b, np.full(len(b), person, np.int64)))
    return out


def draw_sample(data: TrainData, cfg: TrainConfig, rng: np.random.Generator) -> Sample:
    """One augmented training sample on the ``img_size`` canvas."""
    if data.cutouts and rng.random() < cfg.copy_paste:
        from vslam.train.copy_paste import crop_sample, paste

        bg = data.backgrounds[int(rng.integers(len(data.backgrounds)))]
        if not len(bg.boxes):  # an unlabelled frame: a random 4:3 window of it
            bg = crop_sample(bg, rng)
        lo, hi = cfg.paste_people
        s = paste(bg, data.cutouts, cfg.classes.index("person"), rng, int(rng.integers(lo, hi + 1)),
                  closeup=cfg.paste_closeup, tilt=cfg.paste_tilt, occluded=cfg.paste_occluded)
    else:
        s = data.samples[int(rng.integers(len(data.samples)))]
    if cfg.grey > 0 and rng.random() < cfg.grey:
        s = replace(s, image=cv2.cvtColor(cv2.cvtColor(s.image, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR))
    return place(s, cfg.img_size, rng)


def _draw(data: TrainData, cfg: TrainConfig, it: int, rank: int | None = None) -> tuple[np.ndarray, ...]:
    """The batch of iteration ``it`` (uint8 images): a function of (seed, it, rank) alone."""
    rng = np.random.default_rng([cfg.seed, it] if rank is None else [cfg.seed, it, rank])
    if not data.cutouts and cfg.grey == 0:  # the recipe before copy-paste: the same draws, the same weights
        samples = [place(data.samples[i], cfg.img_size, rng) for i in rng.integers(0, len(data.samples), cfg.batch)]
    else:
        samples = [draw_sample(data, cfg, rng) for _ in range(cfg.batch)]
    if not cfg.masks:
        return collate_u8(samples)
    return (*collate_u8(samples), *collate_masks(samples, 4), *collate_ignore(samples))  # MaskTargets' order


def _on(arrays: tuple[np.ndarray, ...], dev: torch.device) -> tuple[torch.Tensor, ...]:
    imgs, *rest = (torch.from_numpy(a).to(dev) for a in arrays)
    return (imgs.float().div_(255.0), *rest)


def _batch(data: TrainData, cfg: TrainConfig, it: int, dev: torch.device, rank: int | None = None) -> tuple[torch.Tensor, ...]:
    return _on(_draw(data, cfg, it, rank), dev)


_WORKER: tuple[TrainData, TrainConfig, int | None] | None = None  # set in each batch-drawing child process only


def _init_worker(cfg: TrainConfig, rank: int | None) -> None:
    global _WORKER
    cv2.setNumThreads(1)  # the pool is the parallelism
    _WORKER = (training_data(cfg), cfg, rank)  # deterministic: the parent's samples, rebuilt


def _draw_in_worker(it: int) -> tuple[np.ndarray, ...]:
    data, cfg, rank = _WORKER  # type: ignore[misc]
    return _draw(data, cfg, it, rank)


@contextlib.contextmanager
def _batches(data: TrainData, cfg: TrainConfig, its: range, rank: int | None):
    """Iterator of the batches of ``its`` in order (uint8 numpy). With ``cfg.workers`` a pool of processes draws
    them ahead of the training step (a GPU step outruns one process of copy-paste and augmentation); each batch
    depends on (seed, it, rank) only, so the batches, and the weights, are those of ``workers: 0``. The workers
    are spawned, not forked (a fork after OpenCV's thread pool has run can deadlock the child), and rebuild the
    training data themselves (seeded: the same samples) rather than receive a pickled copy."""
    if cfg.workers <= 0:
        yield (_draw(data, cfg, it, rank) for it in its)
        return
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(cfg.workers, _init_worker, (cfg, rank)) as pool:
        yield _ahead(pool, its, 2 * cfg.workers)


def _ahead(pool, its: range, n: int):
    """``pool``'s batches of ``its`` in order, at most ``n`` drawn ahead of the consumer (``imap`` would draw
    without bound: a few GB of batches if the training step is the slower side)."""
    pending: deque = deque()
    todo = iter(its)
    for it in itertools.islice(todo, n):
        pending.append(pool.apply_async(_draw_in_worker, (it,)))
    while pending:
        batch = pending.popleft().get()
        nxt = next(todo, None)
        if nxt is not None:
            pending.append(pool.apply_async(_draw_in_worker, (nxt,)))
        yield batch


def _recipe(d: dict) -> dict:
    """The config fields that change the trained weights (resume must match them)."""
    return {k: v for k, v in d.items()
            if k not in ("resume", "threads", "workers", "device", "ckpt_every", "log_every", "weights", "evaluate")}


def _resume(last: Path, cfg: TrainConfig, model: YoloDetector, opt: torch.optim.Optimizer, dev: torch.device) -> int:
    """Model and optimiser state from ``last`` (read weights-only: a file planted in the output folder never runs
    code) -> the iteration to continue from."""
    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    what, note = "detector training checkpoint", "resume refused"
    ck = read_checkpoint(last, what, ("model", "optimizer", "iteration", "train"), map_location=dev, note=note)
    with reading(last, what, note):
        if _recipe(dict(ck["train"])) != _recipe(asdict(cfg)):
            raise ConfigError(f"{last}: was trained with a different config; resume needs the same one")
        load_state(model, ck["model"], last, what, note)
        opt.load_state_dict(ck["optimizer"])
        return int(ck["iteration"])


def _load_init(model: YoloDetector, cfg: TrainConfig) -> None:
    """``model`` from the ``init`` checkpoint. A detector without a mask head may start one with a mask head (the
    head's new modules keep their random start); anything else must match exactly."""
    from vslam.dynamic.detector import load_model

    start_model, ck = load_model(cfg.init, "train.init")
    same = replace(start_model.cfg, masks=model.cfg.masks) == model.cfg and start_model.cfg.masks in (0, model.cfg.masks)
    if not same or list(ck["names"]) != list(cfg.classes):
        raise ConfigError(f"{cfg.init}: another architecture or class list than train.{cfg.attention} / {list(cfg.classes)}"
                          f" (masks {cfg.masks})")
    missing, unexpected = model.load_state_dict(start_model.state_dict(), strict=False)
    new = {k for m in mask_head_modules(model) for k in _names_in(model, m)}
    if unexpected or not set(missing) <= new:
        raise ConfigError(f"{cfg.init}: weights do not fit the model (missing {sorted(set(missing) - new)[:3]}, "
                          f"unexpected {unexpected[:3]})")


def _names_in(model: torch.nn.Module, sub: torch.nn.Module) -> list[str]:
    """State-dict keys of ``model`` that belong to its submodule ``sub``."""
    prefix = next(n for n, m in model.named_modules() if m is sub)
    return [k for k in model.state_dict() if k.startswith(prefix + ".")]


def _train_mode(model: YoloDetector, cfg: TrainConfig) -> None:
    """Train mode; a frozen detector stays in eval mode (its BatchNorm statistics must not drift)."""
    if not cfg.freeze_detector:
        model.train()
        return
    model.eval()
    for m in mask_head_modules(model):
        m.train()


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


def train(cfg: TrainConfig, progress: Progress | None = None) -> dict[str, dict[str, float]]:
    """Run (or resume) training; returns the held-out metrics per set ({} on ranks other than 0).
    ``progress(iterations done, iterations)`` on rank 0 after each iteration."""
    cfg = resolve(cfg)
    dev = torch.device("cuda" if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available()) else "cpu")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    return ddp.launch(dev, functools.partial(_train, cfg, progress=progress))


def _train(cfg: TrainConfig, dev: torch.device, rank: int, n_ranks: int,
           progress: Progress | None = None) -> dict[str, dict[str, float]]:
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)  # weight initialisation
    model = YoloDetector(DetectorConfig(cfg.scale, cfg.attention, len(cfg.classes), width=cfg.width, masks=cfg.masks)).to(dev)
    if cfg.init:
        _load_init(model, cfg)
    trained = mask_head_modules(model) if cfg.freeze_detector else [model]
    params = [p for m in trained for p in m.parameters()]
    if cfg.freeze_detector:
        for p in model.parameters():
            p.requires_grad_(False)
        for p in params:
            p.requires_grad_(True)
    net = ddp.wrap(model, dev, n_ranks)  # what the forward pass goes through
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    if cfg.resume and (out / "last.pt").is_file():
        start = _resume(out / "last.pt", cfg, model, opt, dev)
        log.info("resumed at iteration %d", start)
    train_set, val_sets = training_data(cfg), held_out_sets(cfg) if cfg.evaluate else {}
    log.info("training samples: %d (+ %d backgrounds x %d people cutouts); held-out: %s", len(train_set.samples),
             len(train_set.backgrounds), len(train_set.cutouts), {k: len(v) for k, v in val_sets.items()})
    _train_mode(model, cfg)
    lead = rank == 0  # the one rank that writes
    with open(out / "log.csv", "a") if lead else contextlib.nullcontext() as f:
        if start == 0 and lead:
            f.write("iteration,lr,loss,box,cls,dfl,seconds\n" if not cfg.masks else "iteration,lr,loss,box,cls,dfl,mask,seconds\n")
        t0 = time.perf_counter()
        batches = _batches(train_set, cfg, range(start, cfg.iterations), rank if n_ranks > 1 else None)
        with batches as drawn:
            for it, arrays in zip(range(start, cfg.iterations), drawn):
                x, gb, gl, gm, *extra = _on(arrays, dev)
                for g in opt.param_groups:
                    g["lr"] = _lr(cfg, it)
                loss, parts = detection_loss(model, net(x), gb, gl, gm, LossConfig(mask=cfg.mask_gain), MaskTargets(*extra))
                opt.zero_grad(set_to_none=True)
                loss.backward()  # DDP: gradients averaged over the ranks here
                torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
                opt.step()
                if not lead:
                    continue
                if progress is not None:
                    progress(it + 1, cfg.iterations)
                if it % cfg.log_every == 0 or it + 1 == cfg.iterations:
                    mask = f"{parts['mask']:.5f}," if cfg.masks else ""
                    f.write(f"{it},{_lr(cfg, it):.6g},{float(loss.detach()):.5f},{parts['box']:.5f},{parts['cls']:.5f},"
                            f"{parts['dfl']:.5f},{mask}{time.perf_counter() - t0:.1f}\n")
                    f.flush()
                    log.info("it %d loss %.4f %s", it, float(loss.detach()), parts)
                if (it + 1) % cfg.ckpt_every == 0 or it + 1 == cfg.iterations:
                    save_checkpoint(out / "last.pt", model, list(cfg.classes), optimizer=opt.state_dict(),
                                    iteration=it + 1, train=asdict(cfg))
    if n_ranks > 1:
        ddp.check_in_sync(model)
    if not lead:
        return {}
    recalibrate_bn(model, [_batch(train_set, cfg, 10_000_000 + k, dev)[0] for k in range(cfg.bn_batches)],
                   only=mask_head_modules(model) if cfg.freeze_detector else None)
    metrics = {name: evaluate(model, data, cfg, dev) for name, data in val_sets.items()}
    save_checkpoint(out / "model.pt", model, list(cfg.classes), img_size=cfg.img_size, metrics=metrics, train=asdict(cfg))
    if cfg.weights:
        save_checkpoint(cfg.weights, model, list(cfg.classes), half=True, img_size=cfg.img_size, metrics=metrics, train=asdict(cfg))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics
