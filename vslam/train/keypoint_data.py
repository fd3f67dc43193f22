"""Which real images keypoint networks train on and which are held out: the splits of each source, shared by the
trainer (``train_keypoints``), the benchmarks (``evaluate``) and the int8 calibration (``convpoint``), so none of
them imports another to learn them."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeypointSplits:
    """Sources under the data root ("" = none) and the first held-out frame of each; ``frame_stride``: every n-th
    training frame of the sequences (neighbours are near-duplicates)."""

    coco: str = "coco128/images"
    coco_split: int = 100
    tum: str = "tum/rgbd_dataset_freiburg3_teddy"
    tum_split: int = 100
    kitti: str = "kitti/sequences/07"
    kitti_split: int = 80
    euroc: str = "euroc/V1_01_easy_micro"
    euroc_split: int = 48
    frame_stride: int = 2


def sequence_frames(kind: str, path: Path) -> list[Path]:
    """The image files of a COCO folder or a TUM / KITTI / EuRoC sequence, in time (name) order."""
    sub = {"coco": ".", "tum": "rgb", "kitti": "image_0", "euroc": "mav0/cam0/data"}[kind]
    return sorted(p for p in (path / sub).rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))


def image_files(cfg: KeypointSplits, root: Path, held_out: bool) -> dict[str, list[Path]]:
    """The real images of each source, training (before the split) or held-out (from the split on). ``cfg``: the
    splits, or a training config with the same fields (``KeypointTrainConfig``)."""
    out: dict[str, list[Path]] = {}
    srcs = (("coco", cfg.coco, cfg.coco_split), ("tum", cfg.tum, cfg.tum_split), ("kitti", cfg.kitti, cfg.kitti_split),
            ("euroc", cfg.euroc, cfg.euroc_split))
    for name, rel, split in srcs:
        if not rel:
            continue
        if not (root / rel).exists():
            log.warning("%s images not found at %s: %s without them", name, root / rel, "held out" if held_out else "trained")
            continue
        files = sequence_frames(name, root / rel)
        out[name] = files[split:] if held_out else files[:split:1 if name == "coco" else cfg.frame_stride]
    return out
