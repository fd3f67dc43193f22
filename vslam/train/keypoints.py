"""``vslam train keypoints``: ConvPoint trained in SuperPoint's three stages from images we hold.

1. **shapes** -- the keypoint head alone on synthetic shapes with exact corners (``train.shapes``), each
   image seen through a random homography and photometric change (MagicPoint).
2. **adapt** -- homographic adaptation: the stage-1 detector run on ``adapt_homographies`` warps of every
   real training image, the heatmaps averaged back in the image's frame, NMS, thresholded -> pseudo-labels
   that are repeatable by construction.
3. **joint** -- keypoint and descriptor heads on (image, random warp of it) pairs with strong independent
   photometric changes on each side: cell cross-entropy against the (warped) pseudo-labels, and an InfoNCE
   descriptor loss over ``desc_points`` corresponding locations per pair (pseudo-keypoints first, random
   pixels after; negatives closer than ``desc_neg_px`` to the positive in B are not counted).

Real training images (grey, resized to a short side of ``image_short``, random crops of ``size``): COCO128
images before ``coco_split``, TUM fr3/teddy frames before ``tum_split``, KITTI 07 frames before
``kitti_split``, EuRoC V1_01 cam0 frames before ``euroc_split``. The frames after each split are held out
for ``vslam eval-features`` (``eval.keypoints.held_out_images``) and never trained on. No labels or poses
of any real image are used.

Seeded; ``out/last.pt`` every ``ckpt_every`` steps of a stage (``resume`` continues the stage it holds);
``out/log.jsonl`` holds the loss curve; ``toy`` is a tiny CPU smoke run of the same recipe (tests). Mixed precision (bf16) on CUDA. Several GPUs or
CPU processes: ``torchrun --nproc_per_node=N -m vslam.cli train keypoints ...`` (``vslam.ddp``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from vslam.progress import Progress
from vslam.train.keypoint_data import KeypointSplits, image_files

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeypointTrainConfig:
    out: str = "runs/train_keypoints/convpoint"
    weights: str = ""  # also copy the final weights here (e.g. vslam/models/convpoint_v1.pt)
    # start from these ConvPoint weights and skip the shapes stage: a further round of homographic adaptation
    # with the joint detector, then joint training again (SuperPoint's second round)
    init: str = ""
    channels: tuple[int, ...] = (24, 48, 96, 128)
    desc_dim: int = 128
    # stage 1: synthetic shapes
    shapes_steps: int = 2000
    shapes_batch: int = 32
    shapes_size: tuple[int, int] = (120, 160)  # (h, w)
    shapes_pool: int = 6000  # rendered once, then seen through random homographies
    # stage 2: homographic adaptation of the real training images
    adapt_homographies: int = 32
    adapt_thresh: float = 0.015
    adapt_max_points: int = 400
    # stage 3: joint training on warped pairs
    joint_steps: int = 2500
    batch: int = 8
    size: tuple[int, int] = (192, 256)  # (h, w) crops of the real images
    image_short: int = 240
    desc_points: int = 256
    desc_neg_px: float = 8.0
    temperature: float = 0.07
    desc_weight: float = 1.0
    nms_radius: int = 4
    lr: float = 1e-3
    weight_decay: float = 1e-4
    # data (under the data root; "" = none): the splits of ``keypoint_data.KeypointSplits`` unless changed
    coco: str = KeypointSplits.coco
    coco_split: int = KeypointSplits.coco_split
    tum: str = KeypointSplits.tum
    tum_split: int = KeypointSplits.tum_split
    kitti: str = KeypointSplits.kitti
    kitti_split: int = KeypointSplits.kitti_split
    euroc: str = KeypointSplits.euroc
    euroc_split: int = KeypointSplits.euroc_split
    frame_stride: int = KeypointSplits.frame_stride
    seed: int = 0
    threads: int = 2
    device: str = "auto"
    ckpt_every: int = 100
    log_every: int = 50
    resume: bool = False
    toy: bool = False

    def __post_init__(self) -> None:
        from vslam.errors import ConfigError

        if min(self.shapes_steps, self.joint_steps, self.batch, self.shapes_batch, self.adapt_homographies) < 1:
            raise ConfigError("train keypoints: steps, batches and adapt_homographies must be >= 1")
        for name in ("size", "shapes_size"):
            v = getattr(self, name)
            if len(v) != 2 or v[0] % 8 or v[1] % 8:
                raise ConfigError(f"train keypoints: {name} must be (h, w) multiples of 8, got {list(v)}")


def toy_config(cfg: KeypointTrainConfig) -> KeypointTrainConfig:
    """The smoke-run scale: small enough for a test, long enough (40 joint steps of 2 pairs) that the
    descriptor loss falls past its noise."""
    return dataclasses.replace(cfg, channels=(8, 16, 16, 32), desc_dim=32, shapes_steps=min(cfg.shapes_steps, 60),
                               shapes_batch=8, shapes_size=(64, 80), shapes_pool=64, adapt_homographies=3,
                               joint_steps=min(cfg.joint_steps, 40), batch=2, size=(64, 80), image_short=80,
                               desc_points=32, coco="", tum="", kitti="", euroc="", ckpt_every=10, log_every=10)


# ---------------------------------------------------------------------------------------------- targets, losses


def cell_targets(xy: np.ndarray, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """(h/8, w/8) int64 class per cell: the in-cell position (0..63) of one keypoint in it, picked at random
    when several fall in the cell, 64 ("no keypoint") when none."""
    t = np.full((h // 8, w // 8), 64, np.int64)
    if len(xy) == 0:
        return t
    ij = np.round(xy).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    ij = ij[ok][rng.permutation(int(ok.sum()))]
    t[ij[:, 1] // 8, ij[:, 0] // 8] = (ij[:, 1] % 8) * 8 + ij[:, 0] % 8  # the last write of a cell wins
    return t


def detector_loss(logits, target, valid=None):
    """Cell cross-entropy; ``valid`` (B,Hc,Wc) bool leaves out cells outside a warped image."""
    import torch.nn.functional as F

    ce = F.cross_entropy(logits.float(), target, reduction="none")
    if valid is None:
        return ce.mean()
    v = valid.float()
    return (ce * v).sum() / v.sum().clamp_min(1.0)


def descriptor_loss(desc_a, desc_b, pa, pb, n_valid, temperature: float, neg_px: float):
    """Symmetric InfoNCE over corresponding pixels. desc_*: (B,D,Hc,Wc); pa, pb: (B,N,2) pixels of A and
    their images in B; n_valid: (B,) how many of the N rows are real correspondences."""
    import torch
    import torch.nn.functional as F

    from vslam.features.convpoint import sample_descriptors

    da, db = sample_descriptors(desc_a.float(), pa), sample_descriptors(desc_b.float(), pb)
    losses = []
    for b in range(len(da)):
        n = int(n_valid[b])
        if n < 2:
            continue
        s = da[b, :n] @ db[b, :n].T / temperature
        near = torch.cdist(pb[b, :n], pb[b, :n]) < neg_px
        s = s.masked_fill(near & ~torch.eye(n, dtype=torch.bool, device=s.device), float("-inf"))
        lab = torch.arange(n, device=s.device)
        losses.append(0.5 * (F.cross_entropy(s, lab) + F.cross_entropy(s.T, lab)))
    return torch.stack(losses).mean() if losses else desc_a.sum() * 0.0


# ---------------------------------------------------------------------------------------------- data


def _read_grey(path: Path, short: int) -> np.ndarray | None:
    im = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if im is None:
        return None
    s = short / min(im.shape[:2])
    return cv2.resize(im, (round(im.shape[1] * s), round(im.shape[0] * s)), interpolation=cv2.INTER_AREA)


def training_images(cfg: KeypointTrainConfig, root: Path) -> list[np.ndarray]:
    ims = [_read_grey(f, cfg.image_short) for fs in image_files(cfg, root, held_out=False).values() for f in fs]
    return [im for im in ims if im is not None and im.shape[0] >= cfg.size[0] and im.shape[1] >= cfg.size[1]]


def toy_images(rng: np.random.Generator, n: int, h: int, w: int) -> list[np.ndarray]:
    """Stand-ins for real images in the toy run: larger synthetic shapes scenes."""
    from vslam.train.shapes import render_shapes

    return [render_shapes(rng, h, w)[0] for _ in range(n)]


def _crop(rng, im: np.ndarray, pts: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    y0 = int(rng.integers(0, im.shape[0] - h + 1))
    x0 = int(rng.integers(0, im.shape[1] - w + 1))
    p = pts - [x0, y0]
    keep = (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)
    return im[y0:y0 + h, x0:x0 + w], p[keep]


# ---------------------------------------------------------------------------------------------- stages


def homographic_adaptation(model, image: np.ndarray, n: int, rng: np.random.Generator, dev, spec=None) -> np.ndarray:
    """(h,w) keypoint probability of ``image`` averaged over ``n`` random views (the first the identity)."""
    import torch

    from vslam.eval.homography import HomographySpec, random_homography, warp
    from vslam.features.convpoint import batch_tensor, heatmap

    h, w = image.shape
    Hs = [np.eye(3)] + [random_homography(rng, h, w, spec or HomographySpec()) for _ in range(n - 1)]
    views = [warp(image, H) for H in Hs]
    acc, cnt = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    with torch.inference_mode():
        for i in range(0, n, 16):
            x, _ = batch_tensor(views[i:i + 16])
            heat = heatmap(model(x.to(dev))[0])[:, :h, :w].float().cpu().numpy()
            for k, H in enumerate(Hs[i:i + 16]):
                Hinv = np.linalg.inv(H)
                valid = cv2.warpPerspective(np.ones((h, w), np.float32), H, (w, h), flags=cv2.INTER_NEAREST)
                acc += cv2.warpPerspective(heat[k] * valid, Hinv, (w, h), flags=cv2.INTER_LINEAR)
                cnt += cv2.warpPerspective(valid, Hinv, (w, h), flags=cv2.INTER_NEAREST)
    return acc / np.maximum(cnt, 1.0)


def pseudo_labels(heat: np.ndarray, thresh: float, nms_radius: int, max_points: int, border: int = 4) -> np.ndarray:
    """(N,2) pixel keypoints of an aggregated heatmap: NMS, threshold, the strongest ``max_points``."""
    import torch

    from vslam.features.convpoint import nms

    p = nms(torch.from_numpy(heat)[None], nms_radius)[0].numpy()
    if border:
        p[:border] = p[-border:] = 0
        p[:, :border] = p[:, -border:] = 0
    ys, xs = np.nonzero(p >= thresh)
    order = np.lexsort((np.arange(len(xs)), -p[ys, xs]))[:max_points]
    return np.stack([xs[order], ys[order]], axis=1).astype(np.float64)


def _shapes_batch(cfg, pool, rng):
    from vslam.eval.homography import HomographySpec, photometric, random_homography, valid_mask, warp, warp_points

    h, w = cfg.shapes_size
    ims, tg, va = [], [], []
    for _ in range(cfg.shapes_batch):
        im, pts = pool[int(rng.integers(len(pool)))]
        H = random_homography(rng, h, w, HomographySpec(scale=(0.8, 1.2), rotation_deg=30, perspective=0.1, shift=0.1))
        ims.append(photometric(warp(im, H), rng, 0.7))
        tg.append(cell_targets(warp_points(H, pts), h, w, rng))
        va.append(_cell_valid(valid_mask(H, h, w)))
    return ims, np.stack(tg), np.stack(va)


def _cell_valid(mask: np.ndarray) -> np.ndarray:
    """(h/8, w/8) cells with at least 3/4 of their pixels inside the warped image."""
    h, w = mask.shape
    return mask.reshape(h // 8, 8, w // 8, 8).mean(axis=(1, 3)) >= 0.75


def _joint_batch(cfg, images, labels, rng):
    from vslam.eval.homography import inside, photometric, random_homography, valid_mask, warp, warp_points

    h, w = cfg.size
    ims_a, ims_b, ta, tb, vb, pa, pb, nv = [], [], [], [], [], [], [], []
    for _ in range(cfg.batch):
        k = int(rng.integers(len(images)))
        a, pts = _crop(rng, images[k], labels[k], h, w)
        H = random_homography(rng, h, w)
        b = warp(a, H)
        ims_a.append(photometric(a, rng))
        ims_b.append(photometric(b, rng))
        ta.append(cell_targets(pts, h, w, rng))
        pts_b = warp_points(H, pts)
        tb.append(cell_targets(pts_b, h, w, rng))
        vm = valid_mask(H, h, w)
        vb.append(_cell_valid(vm))
        # correspondences: pseudo-keypoints first, then random pixels; both must land inside B
        rnd = rng.uniform([0, 0], [w - 1, h - 1], (cfg.desc_points, 2))
        cand = np.vstack([pts[rng.permutation(len(pts))], rnd])
        cb = warp_points(H, cand)
        ok = inside(cb, h, w, 4)
        ij = np.round(cb[ok]).astype(np.int64)
        ok[ok] = vm[ij[:, 1], ij[:, 0]]
        cand, cb = cand[ok][: cfg.desc_points], cb[ok][: cfg.desc_points]
        n = len(cand)
        pa.append(np.vstack([cand, np.zeros((cfg.desc_points - n, 2))]))
        pb.append(np.vstack([cb, np.zeros((cfg.desc_points - n, 2))]))
        nv.append(n)
    return ims_a + ims_b, np.stack(ta + tb), np.stack([np.ones_like(vb[0])] * cfg.batch + vb), np.stack(pa), np.stack(pb), np.array(nv)


def train(cfg: KeypointTrainConfig, progress: Progress | None = None) -> dict:
    """Run (or resume) the three stages -> metrics ({} on DDP ranks other than 0). ``progress(steps done, steps)``
    on rank 0 after each step of the two training stages, counted together (adaptation between them has none)."""
    import torch

    from vslam import ddp

    if cfg.toy:
        cfg = toy_config(cfg)
    torch.set_num_threads(max(1, cfg.threads))
    dev = torch.device("cuda" if cfg.device in ("auto", "cuda") and torch.cuda.is_available() else "cpu")
    return ddp.launch(dev, functools.partial(_train, cfg, progress=progress))


def _optim(model, lr, wd, steps):
    import torch

    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=wd)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=max(0.05, 3 / steps))
    return opt, sched


RESUME_WHAT = "keypoint training checkpoint"


def _resume(last: Path, model, dev) -> dict:
    """``last``'s dict with its model state applied (read weights-only: a file planted in the output folder never
    runs code). Optimiser, schedule and RNG states are applied by the stage they belong to."""
    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    keys = ("model", "opt", "sched", "rng", "torch_rng", "stage", "step", "history")
    ck = read_checkpoint(last, RESUME_WHAT, keys, map_location=dev, note="resume refused")
    with reading(last, RESUME_WHAT, "resume refused"):
        if ck["stage"] not in ("shapes", "adapt", "joint"):
            raise ValueError(f"unknown stage {ck['stage']!r}")
        load_state(model, ck["model"], last, RESUME_WHAT, "resume refused")
        ck["step"] = int(ck["step"])
        ck["history"] = {str(k): [float(x) for x in v] for k, v in dict(ck["history"]).items()}
    return ck


def _train(cfg: KeypointTrainConfig, dev, rank: int, n_ranks: int, progress: Progress | None = None) -> dict:
    import torch

    from vslam import ddp
    from vslam.features.convpoint import ConvPointConfig, ConvPointNet, batch_tensor, save_convpoint
    from vslam.nn.checkpoint import reading
    from vslam.paths import data_root
    from vslam.train.shapes import render_shapes

    torch.manual_seed(cfg.seed)
    lead = rank == 0
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    last = out / "last.pt"
    model = ConvPointNet(ConvPointConfig(tuple(cfg.channels), cfg.desc_dim)).to(dev)
    if cfg.init:
        from vslam.features.convpoint import load_convpoint

        start = load_convpoint(cfg.init)
        if start.cfg != model.cfg:
            from vslam.errors import ConfigError

            raise ConfigError(f"train keypoints: init {cfg.init} has channels {list(start.cfg.channels)} / desc_dim "
                              f"{start.cfg.desc_dim}, the config {list(cfg.channels)} / {cfg.desc_dim}")
        model.load_state_dict(start.state_dict())
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if dev.type == "cuda" else torch.autocast("cpu", enabled=False)
    state = {"stage": "adapt" if cfg.init else "shapes", "step": 0, "history": {"shapes": [], "joint_det": [], "joint_desc": []}}
    ck = _resume(last, model, dev) if cfg.resume and last.exists() else None
    if ck is not None:
        state = {k: ck[k] for k in ("stage", "step", "history")}
        log.info("resumed %s at step %d", state["stage"], state["step"])
    t_start = time.perf_counter()
    times = {}
    before = {"shapes": 0, "joint": 0 if cfg.init else cfg.shapes_steps}  # steps of the stages before each one
    total_steps = before["joint"] + cfg.joint_steps

    def save(opt, sched, rng):
        if lead:
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(), **state}, last)

    def run_stage(name: str, steps: int, lr: float, batch_fn, loss_fn):
        net = ddp.wrap(model, dev, n_ranks, find_unused=name == "shapes")  # stage 1 leaves the descriptor head alone
        opt, sched = _optim(model, lr, cfg.weight_decay, steps)
        rng = np.random.default_rng([cfg.seed, rank, {"shapes": 1, "joint": 3}[name]])
        if ck is not None and ck["stage"] == name:
            with reading(last, RESUME_WHAT, "resume refused"):
                opt.load_state_dict(ck["opt"])
                sched.load_state_dict(ck["sched"])
                rng.bit_generator.state = ck["rng"]
                torch.set_rng_state(ck["torch_rng"].cpu())
        t0 = time.perf_counter()
        model.train()
        while state["step"] < steps:
            batch = batch_fn(rng)
            with amp:
                loss, parts = loss_fn(net, batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            state["step"] += 1
            for k, v in parts.items():
                state["history"][k].append(v)
            if lead and progress is not None:
                progress(before[name] + state["step"], total_steps)
            if lead and state["step"] % cfg.log_every == 0:
                means = {k: float(np.mean(state["history"][k][-cfg.log_every:])) for k in parts}
                per_step = (time.perf_counter() - t0) / max(state["step"], 1)
                log.info("%s step %d/%d %s (%.2f s/step)", name, state["step"], steps,
                         ", ".join(f"{k} {v:.4f}" for k, v in means.items()), per_step)
                with open(out / "log.jsonl", "a") as fh:  # the training curve, one line per log_every steps
                    fh.write(json.dumps({"stage": name, "step": state["step"], **means, "s_per_step": per_step}) + "\n")
            if state["step"] % cfg.ckpt_every == 0 or state["step"] == steps:
                save(opt, sched, rng)
        times[name] = time.perf_counter() - t0

    # ---- stage 1: shapes
    if state["stage"] == "shapes":
        prng = np.random.default_rng([cfg.seed, 100])
        t0 = time.perf_counter()
        pool = [render_shapes(prng, *cfg.shapes_size) for _ in range(cfg.shapes_pool)]
        log.info("rendered %d shapes images (%.1f s)", len(pool), time.perf_counter() - t0)

        def shapes_loss(net, batch):
            ims, tg, va = batch
            x, _ = batch_tensor(ims)
            logits, _ = net(x.to(dev))
            loss = detector_loss(logits, torch.from_numpy(tg).to(dev), torch.from_numpy(va).to(dev))
            return loss, {"shapes": loss.item()}

        run_stage("shapes", cfg.shapes_steps, cfg.lr, lambda rng: _shapes_batch(cfg, pool, rng), shapes_loss)
        state.update(stage="adapt", step=0)

    # ---- stage 2: homographic adaptation (pseudo-labels cached in out/pseudo.npz)
    root = data_root()
    arng = np.random.default_rng([cfg.seed, 2])
    images = toy_images(arng, 6, 96, 128) if cfg.toy else training_images(cfg, root)
    if not images:
        from vslam.errors import ConfigError

        raise ConfigError(f"train keypoints: no real training images under {root} (set VSLAM_DATA, or --toy)")
    cache = out / "pseudo.npz"
    if state["stage"] == "adapt" or not cache.exists():
        t0 = time.perf_counter()
        model.eval()
        labels = [pseudo_labels(homographic_adaptation(model, im, cfg.adapt_homographies, arng, dev), cfg.adapt_thresh,
                                cfg.nms_radius, cfg.adapt_max_points) for im in images]
        times["adapt"] = time.perf_counter() - t0
        if lead:
            np.savez_compressed(cache, **{f"p{i}": p for i, p in enumerate(labels)})
        log.info("pseudo-labelled %d images, %.0f points each (%.1f s)", len(images), np.mean([len(p) for p in labels]),
                 times["adapt"])
        state.update(stage="joint", step=0)
    else:
        z = np.load(cache)
        labels = [z[f"p{i}"] for i in range(len(images))]

    # ---- stage 3: joint detector + descriptor
    def joint_loss(net, batch):
        ims, tg, va, pa, pb, nv = batch
        x, _ = batch_tensor(ims)
        logits, desc = net(x.to(dev))
        ld = detector_loss(logits, torch.from_numpy(tg).to(dev), torch.from_numpy(va).to(dev))
        n = cfg.batch
        le = descriptor_loss(desc[:n], desc[n:], torch.from_numpy(pa).float().to(dev), torch.from_numpy(pb).float().to(dev),
                             nv, cfg.temperature, cfg.desc_neg_px)
        return ld + cfg.desc_weight * le, {"joint_det": ld.item(), "joint_desc": le.item()}

    run_stage("joint", cfg.joint_steps, cfg.lr, lambda rng: _joint_batch(cfg, images, labels, rng), joint_loss)
    if n_ranks > 1:
        ddp.check_in_sync(model)
    if not lead:
        return {}
    model.eval().cpu()
    hist = state["history"]

    def ends(v):
        n = max(1, min(50, len(v) // 5))
        return (float(np.mean(v[:n])), float(np.mean(v[-n:]))) if v else (None, None)  # a stage this run skipped

    metrics = {"config": asdict(cfg), "parameters": int(sum(p.numel() for p in model.parameters())), "device": str(dev),
               "images": len(images), "pseudo_points_mean": float(np.mean([len(p) for p in labels])),
               "loss": {k: dict(zip(("first", "last"), ends(v))) for k, v in hist.items()},
               "stage_s": times, "train_s": time.perf_counter() - t_start}
    if not cfg.toy:
        from vslam.eval.keypoints import evaluate_convpoint_model

        metrics["eval"] = evaluate_convpoint_model(model, root)
    meta = {k: metrics[k] for k in ("parameters", "device", "images", "loss", "train_s")}
    save_convpoint(model, out / "model.pt", meta)
    if cfg.weights:
        save_convpoint(model, cfg.weights, meta)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=str))
    return metrics


def calibration_inputs(root: Path, per_source: int) -> list:
    """Standardised full-size training images (never the held-out ones), ``per_source`` from each source: what
    the int8 ConvPoint's activation ranges are measured on."""
    from vslam.features.convpoint import batch_tensor, standardize

    out = []
    for fs in image_files(KeypointSplits(), root, held_out=False).values():
        for i in np.unique(np.linspace(0, len(fs) - 1, min(per_source, len(fs))).round().astype(int)) if fs else []:
            im = cv2.imread(str(fs[i]), cv2.IMREAD_GRAYSCALE)
            if im is not None:
                out.append(standardize(batch_tensor([im])[0]))
    return out


def calibrate_convpoint(weights: str | Path, root: Path, per_source: int = 8) -> Path:
    """Activation ranges of the int8 ConvPoint from training images -> ``<weights>.int8.json``."""
    import torch

    from vslam.errors import DatasetError
    from vslam.features.convpoint import INT8_FLOAT_MODULES, _Core, load_convpoint
    from vslam.quantize import calibrate, save_qparams

    inputs = calibration_inputs(root, per_source)
    if not inputs:
        raise DatasetError(root, "no training images to calibrate on (COCO128 / TUM / KITTI / EuRoC subsets; set VSLAM_DATA)")
    qparams = calibrate(_Core(load_convpoint(weights)).eval(), inputs, INT8_FLOAT_MODULES)
    meta = {"images": len(inputs), "per_source": per_source, "split": "training images (train.keypoints)",
            "float_modules": list(INT8_FLOAT_MODULES), "torch": torch.__version__}
    return save_qparams(weights, qparams, meta)
