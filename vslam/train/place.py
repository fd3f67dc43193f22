"""``vslam train place``: VLADNet trained with a triplet loss on places we hold (``vslam.train.place_data``).

Positives and negatives come from ground truth or from construction, never from labels someone drew:

* synthetic looping routes (seeds ``synthetic_seeds``; lighting change on): same place = cameras within
  ``pos_m`` and ``pos_deg``, different place = more than ``neg_m`` apart;
* KITTI 07 frames (``kitti``; ground-truth poses): the same with ``kitti_pos_m`` / ``kitti_neg_m``;
* COCO128 images (``coco``): a place is one image, its positive a second random perspective crop of it;
* TUM fr3/teddy frames before ``tum_split`` (ground truth, ``tum_pos_m`` / ``tum_neg_m``).

Every image gets a random photometric change (gain, gamma, noise, blur) so that the same place under a
different exposure stays close. Held out, never trained on: synthetic seed ``val_seed`` (the bench's loop
route) and the TUM teddy frames from ``tum_split`` on (queries; the database is every frame), where
``vslam bench`` measures recall against the BoW baseline.

Per step: ``batch`` anchors, one positive each and ``negatives`` negatives, of which the hardest counts (a
margin triplet loss on squared distances of unit vectors). NetVLAD clusters start at k-means centres of the
(randomly initialised) backbone's features. Seeded; ``out/last.pt`` every ``ckpt_every`` steps (``resume``);
``toy`` is a tiny CPU smoke run of the same recipe (tests). Several GPUs or CPU processes:
``torchrun --nproc_per_node=N -m vslam.cli train place ...`` (``vslam.ddp``: each rank draws its own triplets,
gradients are averaged, rank 0 writes); without torchrun nothing changes.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from vslam.progress import Progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlaceTrainConfig:
    out: str = "runs/train_place/vladnet"
    weights: str = ""  # also copy the final weights here (e.g. vslam/models/vladnet_v1.pt)
    synthetic_seeds: tuple[int, ...] = (11, 12, 13, 14, 15, 16)
    synthetic_frames: int = 600
    synthetic_stride: int = 3
    synthetic_size: tuple[int, int] = (320, 240)
    synthetic_speed: float = 1.4  # m/s: 600 frames at 30 Hz are 2+ laps of the room
    val_seed: int = 0
    pos_m: float = 0.5
    pos_deg: float = 30.0
    neg_m: float = 2.0
    kitti: str = "kitti/sequences/07"  # under the data root; "" = none
    kitti_pos_m: float = 3.0
    kitti_neg_m: float = 20.0
    coco: str = "coco128/images"  # under the data root; "" = none
    # TUM teddy: frames before tum_split train (pairs among them), frames from tum_split on are the held-out
    # queries, ranked against every frame >= tum_exclude_frames away in time; "" = none
    tum: str = "tum/rgbd_dataset_freiburg3_teddy"
    tum_split: int = 100
    tum_pos_m: float = 0.3
    tum_neg_m: float = 1.0
    tum_exclude_frames: int = 30
    channels: tuple[int, ...] = (16, 32, 64, 96)
    clusters: int = 16
    out_dim: int = 256
    input_size: tuple[int, int] = (160, 120)
    steps: int = 1500
    batch: int = 8
    negatives: int = 4
    margin: float = 0.1
    lr: float = 1e-3
    weight_decay: float = 1e-4
    mix: tuple[float, ...] = (0.2, 0.15, 0.3, 0.35)  # share of anchors from synthetic / KITTI / COCO / TUM train split
    kmeans_images: int = 200
    seed: int = 0
    threads: int = 2
    device: str = "auto"
    ckpt_every: int = 100
    log_every: int = 50
    resume: bool = False
    toy: bool = False

    def __post_init__(self) -> None:
        from vslam.errors import ConfigError

        if len(self.mix) != 4 or min(self.mix) < 0 or sum(self.mix) <= 0:
            raise ConfigError(f"train place: mix must be 4 shares >= 0 (synthetic, KITTI, COCO, TUM), got {list(self.mix)}")
        if self.steps < 1 or self.batch < 1 or self.negatives < 1:
            raise ConfigError("train place: steps, batch and negatives must be >= 1")


def toy_config(cfg: PlaceTrainConfig) -> PlaceTrainConfig:
    import dataclasses

    return dataclasses.replace(cfg, synthetic_seeds=(11, 12), synthetic_frames=240, synthetic_stride=4, synthetic_speed=3.5,
                               synthetic_size=(160, 120), kitti="", coco="", tum="", steps=min(cfg.steps, 300), batch=4,
                               negatives=2, kmeans_images=30, ckpt_every=10, log_every=10, clusters=8,
                               channels=(8, 16, 24, 32), out_dim=64, input_size=(80, 60), neg_m=1.0)


class _Pool:
    """Images of one source with a positive / negative sampler."""

    def __init__(self, name: str, images: list, pos: np.ndarray | None, neg: np.ndarray | None):
        self.name, self.images, self.pos, self.neg = name, images, pos, neg
        if pos is not None:
            self.anchors = np.flatnonzero((pos & ~np.eye(len(images), dtype=bool)).any(axis=1) & neg.any(axis=1))
        else:
            self.anchors = np.arange(len(images))

    def triplet(self, rng: np.random.Generator, n_neg: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        a = int(rng.choice(self.anchors))
        if self.pos is None:  # COCO: the positive is another view of the same image
            negs = rng.choice(np.delete(np.arange(len(self.images)), a), n_neg, replace=False)
            return _view(self.images[a], rng), _view(self.images[a], rng), [_view(self.images[int(k)], rng) for k in negs]
        p = int(rng.choice(np.flatnonzero(self.pos[a] & (np.arange(len(self.images)) != a))))
        negs = rng.choice(np.flatnonzero(self.neg[a]), n_neg, replace=True)
        return self.images[a], self.images[p], [self.images[int(k)] for k in negs]


def _view(im: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random perspective crop (a different viewpoint of a planar scene) at 4:3."""
    h, w = im.shape[:2]
    cw, ch = min(w, int(h * 4 / 3)), min(h, int(w * 3 / 4))
    s = rng.uniform(0.6, 0.9)
    bw, bh = cw * s, ch * s
    x0, y0 = rng.uniform(0, w - bw), rng.uniform(0, h - bh)
    src = np.array([[x0, y0], [x0 + bw, y0], [x0 + bw, y0 + bh], [x0, y0 + bh]], np.float32)
    src += rng.normal(0, 0.04 * bw, src.shape).astype(np.float32)
    dst = np.array([[0, 0], [319, 0], [319, 239], [0, 239]], np.float32)
    return cv2.warpPerspective(im, cv2.getPerspectiveTransform(src, dst), (320, 240), borderMode=cv2.BORDER_REFLECT)


def photometric(im: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Gain, gamma, Gaussian noise and (sometimes) blur of a uint8 image."""
    x = (cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im).astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.5, 1.5), 0, 1) ** rng.uniform(0.6, 1.6)
    x = x + rng.normal(0, rng.uniform(0, 0.04), x.shape)
    out = (np.clip(x, 0, 1) * 255).astype(np.uint8)
    if rng.random() < 0.3:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.5))
    return out


def _gt_pool(name: str, s, pos_m: float, pos_deg: float, neg_m: float, facing_away: bool) -> _Pool:
    """A pool from ground truth: same place within ``pos_m`` / ``pos_deg``; different beyond ``neg_m`` or, with
    ``facing_away``, looking the other way (optical axes > 90 deg apart)."""
    from vslam.train.place_data import same_place

    neg = np.linalg.norm(s.positions[:, None] - s.positions[None], axis=2) > neg_m
    if facing_away:
        neg |= s.axes @ s.axes.T < 0
    return _Pool(name, s.images, same_place(s, s, pos_m, pos_deg), neg)


def _pools(cfg: PlaceTrainConfig, root: Path) -> list[_Pool]:
    from vslam.train.place_data import sequence_places, synthetic_route

    pools = []
    for seed in cfg.synthetic_seeds:  # one pool per route: places of different rooms are never compared
        r = synthetic_route(seed, cfg.synthetic_frames, cfg.synthetic_size, cfg.synthetic_stride, speed=cfg.synthetic_speed)
        pools.append(_gt_pool(r.name, r, cfg.pos_m, cfg.pos_deg, cfg.neg_m, facing_away=True))
    if cfg.kitti and (root / cfg.kitti).exists():
        pools.append(_gt_pool("kitti", sequence_places(root / cfg.kitti), cfg.kitti_pos_m, cfg.pos_deg, cfg.kitti_neg_m,
                              facing_away=False))
    elif cfg.kitti:
        log.warning("KITTI frames not found at %s: trained without them", root / cfg.kitti)
    if cfg.tum and (root / cfg.tum).exists():
        t = sequence_places(root / cfg.tum)
        pools.append(_gt_pool("tum", t.subset(t.index < cfg.tum_split), cfg.tum_pos_m, cfg.pos_deg, cfg.tum_neg_m,
                              facing_away=True))
    elif cfg.tum:
        log.warning("TUM frames not found at %s: trained without them", root / cfg.tum)
    if cfg.coco and (root / cfg.coco).exists():
        files = sorted(p for p in (root / cfg.coco).rglob("*") if p.suffix.lower() in (".jpg", ".png"))
        ims = [im for im in (cv2.imread(str(f)) for f in files) if im is not None]
        pools.append(_Pool("coco", ims, None, None))
    elif cfg.coco:
        log.warning("COCO images not found at %s: trained without them", root / cfg.coco)
    return pools


def _kmeans(x, k: int, iters: int, gen):
    import torch

    c = x[torch.randperm(len(x), generator=gen)[:k]].clone()
    for _ in range(iters):
        a = torch.cdist(x, c).argmin(dim=1)
        for j in range(k):
            m = a == j
            if m.any():
                c[j] = x[m].mean(dim=0)
    return torch.nn.functional.normalize(c, dim=1)


def held_out(cfg: PlaceTrainConfig, root: Path) -> dict:
    """The held-out evaluation sets of this recipe (``retrieval.held_out_sets``), built once per run."""
    from vslam.eval.place import held_out_sets

    return held_out_sets(cfg.val_seed, cfg.synthetic_frames, cfg.synthetic_size, cfg.synthetic_stride, cfg.synthetic_speed,
                         cfg.pos_m, cfg.pos_deg, root / cfg.tum if cfg.tum else None, cfg.tum_split, cfg.tum_pos_m,
                         cfg.tum_exclude_frames)


def evaluate(model, sets: dict, with_bow: bool = False) -> dict:
    """Held-out recall@1/5/10 of ``model`` (and the BoW baseline) on ``held_out`` sets."""
    from vslam.eval.place import bow_describer, evaluate_held_out
    from vslam.loop.vladnet import VladNetDescriptor

    desc = {"vladnet": VladNetDescriptor(model).describe_many}
    if with_bow:
        desc["bow"] = bow_describer()
    return evaluate_held_out(desc, sets)


def train(cfg: PlaceTrainConfig, progress: Progress | None = None) -> dict:
    """Run (or resume) training -> metrics ({} on DDP ranks other than 0; ``vslam.ddp``). ``progress(steps done,
    steps)`` on rank 0 after each step."""
    import torch

    from vslam import ddp

    if cfg.toy:
        cfg = toy_config(cfg)
    torch.set_num_threads(max(1, cfg.threads))
    dev = torch.device("cuda" if cfg.device in ("auto", "cuda") and torch.cuda.is_available() else "cpu")
    return ddp.launch(dev, functools.partial(_train, cfg, progress=progress))


def _resume(last: Path, model, opt, sched, rng: np.random.Generator, dev) -> tuple[int, list[float]]:
    """Model, optimiser, schedule and RNG states from ``last`` (read weights-only: a file planted in the output
    folder never runs code) -> (step, loss history)."""
    import torch

    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    what, note = "place training checkpoint", "resume refused"
    keys = ("model", "opt", "sched", "step", "history", "rng", "torch_rng")
    ck = read_checkpoint(last, what, keys, map_location=dev, note=note)
    with reading(last, what, note):
        if "stage" in ck:  # a keypoint trainer's last.pt holds the same keys and one more
            raise ValueError("a keypoint training checkpoint")
        load_state(model, ck["model"], last, what, note)
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        rng.bit_generator.state = ck["rng"]
        torch.set_rng_state(ck["torch_rng"].cpu())
        return int(ck["step"]), [float(x) for x in ck["history"]]


def _train(cfg: PlaceTrainConfig, dev, rank: int, n_ranks: int, progress: Progress | None = None) -> dict:
    import torch

    from vslam import ddp
    from vslam.loop.vladnet import VladNet, VladNetConfig, preprocess, save_vladnet
    from vslam.paths import data_root

    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    lead = rank == 0  # the one rank that writes and evaluates
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    root = data_root()
    model = VladNet(VladNetConfig(tuple(cfg.channels), cfg.clusters, cfg.out_dim, tuple(cfg.input_size))).to(dev)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=cfg.steps, pct_start=max(0.05, 3 / cfg.steps))
    step, history = 0, []
    last = out / "last.pt"
    resumed = cfg.resume and last.exists()
    if resumed:  # before the pools are built: a file that cannot be resumed fails at once
        step, history = _resume(last, model, opt, sched, rng, dev)
        log.info("resumed at step %d", step)
    t0 = time.perf_counter()
    pools = _pools(cfg, root)  # numpy only, seeded by the config: the torch and numpy RNG streams are untouched
    log.info("place pools: %s (%.1f s)", ", ".join(f"{p.name} {len(p.images)}" for p in pools), time.perf_counter() - t0)
    if not resumed:  # NetVLAD clusters from k-means on backbone features of random training images
        gen = torch.Generator().manual_seed(cfg.seed)
        pick = [(p, int(rng.integers(len(p.images)))) for p in (pools[int(rng.integers(len(pools)))] for _ in range(cfg.kmeans_images))]
        with torch.no_grad():
            model.eval()
            f = model.features(preprocess([photometric(p.images[i], rng) for p, i in pick], cfg.input_size).to(dev))
            f = torch.nn.functional.normalize(f, dim=1).permute(0, 2, 3, 1).reshape(-1, f.shape[1]).cpu()
            f = f[torch.randperm(len(f), generator=gen)[:20000]]
            model.vlad.init_clusters(_kmeans(f, cfg.clusters, 20, gen).to(dev))
    eval_init, val_sets = None, held_out(cfg, root) if lead else {}
    if step == 0 and lead:  # the same held-out recall before training (k-means clusters only): what training adds
        eval_init = evaluate(model.eval(), val_sets)
    net = ddp.wrap(model, dev, n_ranks)  # DDP broadcasts rank 0's (identical) start here
    if n_ranks > 1:  # each rank draws its own triplets: the global batch is n_ranks x batch
        rng = np.random.default_rng([cfg.seed, rank, step])
    shares = np.array(cfg.mix, dtype=np.float64)
    names = ("synthetic", "kitti", "coco", "tum")
    kinds = {k: [p for p in pools if p.name.startswith(k)] for k in names}
    avail = np.array([bool(kinds[k]) for k in names])
    shares = shares * avail
    shares /= shares.sum()
    model.train()
    t_train = time.perf_counter()
    while step < cfg.steps:
        imgs = []
        for _ in range(cfg.batch):
            kind = names[int(rng.choice(len(names), p=shares))]
            pool = kinds[kind][int(rng.integers(len(kinds[kind])))]
            a, p, negs = pool.triplet(rng, cfg.negatives)
            imgs += [a, p, *negs]
        x = preprocess([photometric(im, rng) for im in imgs], cfg.input_size).to(dev)
        d = net(x).view(cfg.batch, 2 + cfg.negatives, -1)
        d_pos = (d[:, 0] - d[:, 1]).pow(2).sum(-1)
        d_neg = (d[:, :1] - d[:, 2:]).pow(2).sum(-1).min(dim=1).values  # the hardest negative
        loss = torch.relu(d_pos - d_neg + cfg.margin).mean()
        opt.zero_grad()
        loss.backward()  # DDP: gradients averaged over the ranks here
        opt.step()
        sched.step()
        step += 1
        history.append(loss.item())
        if not lead:
            continue
        if progress is not None:
            progress(step, cfg.steps)
        if step % cfg.log_every == 0:
            log.info("step %d/%d loss %.4f (%.2f s/step)", step, cfg.steps, float(np.mean(history[-cfg.log_every:])),
                     (time.perf_counter() - t_train) / step)
        if step % cfg.ckpt_every == 0 or step == cfg.steps:
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "step": step,
                        "history": history, "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state()}, last)
    if n_ranks > 1:
        ddp.check_in_sync(model)
    if not lead:
        return {}
    model.eval().cpu()
    n_first = max(1, min(50, len(history) // 5))
    metrics = {"config": asdict(cfg), "steps": step, "loss_first": float(np.mean(history[:n_first])),
               "loss_last": float(np.mean(history[-n_first:])), "train_s": time.perf_counter() - t_train,
               "parameters": int(sum(p.numel() for p in model.parameters())),
               "pools": {p.name: len(p.images) for p in pools}, "device": str(dev)}
    metrics["eval"] = evaluate(model, val_sets, with_bow=not cfg.toy)
    if eval_init is not None:
        metrics["eval_init"] = eval_init
    meta = {k: metrics[k] for k in ("steps", "loss_first", "loss_last", "train_s", "parameters", "pools", "device")}
    save_vladnet(model, out / "model.pt", meta)
    if cfg.weights:
        save_vladnet(model, cfg.weights, meta)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
    return metrics
