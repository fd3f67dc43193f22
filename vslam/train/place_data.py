"""Place-recognition data: images with ground-truth camera positions and viewing directions.

Two sources (VLADNet training, docs/loop.md): synthetic looping routes rendered here (seeded; a lighting change
makes the same place look different on each lap) and real sequences read through ``open_sequence`` (frames with a
ground-truth pose). Two frames show the same place when their cameras are within ``pos_m`` metres and their
optical axes within ``pos_deg`` degrees; they show different places beyond ``neg_m``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class PlaceSet:
    """images: list of (H,W[,3]) uint8; positions (N,3) m; axes (N,3) unit optical axes (world); index (N,) frame
    numbers (for temporal exclusion)."""

    name: str
    images: list
    positions: np.ndarray
    axes: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, m: np.ndarray) -> PlaceSet:
        idx = np.flatnonzero(m) if np.asarray(m).dtype == bool else np.asarray(m)
        return PlaceSet(self.name, [self.images[i] for i in idx], self.positions[idx], self.axes[idx], self.index[idx])


def same_place(a: PlaceSet, b: PlaceSet, pos_m: float, pos_deg: float) -> np.ndarray:
    """(len(a), len(b)) bool: the two cameras see the same place."""
    d = np.linalg.norm(a.positions[:, None] - b.positions[None], axis=2)
    cos = np.clip(a.axes @ b.axes.T, -1.0, 1.0)
    return (d < pos_m) & (cos > np.cos(np.radians(pos_deg)))


def synthetic_route(seed: int, n_frames: int = 600, size: tuple[int, int] = (320, 240), stride: int = 1,
                    lighting_change: bool = True, speed: float = 1.4, scene: str = "room") -> PlaceSet:
    """A looping synthetic route (2+ laps at ``speed``), every ``stride``-th frame, BGR images at ``size``."""
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

    w, h = size
    f = 262.5 * w / 320
    cfg = SyntheticConfig(scene=scene, n_frames=n_frames, width=w, height=h, fx=f, fy=f, seed=seed, n_movers=0,
                          loop=True, speed=speed, lighting_change=lighting_change)
    seq = SyntheticSequence(cfg, sensor="mono")
    idx = np.arange(0, n_frames, stride)
    imgs, T = [], []
    for i in idx:
        r = seq.render(int(i), movers=False, right=False)
        imgs.append(r.image)
        T.append(r.T_world_cam)
    T = np.array(T)
    return PlaceSet(f"synthetic_{scene}_seed{seed}", imgs, T[:, :3, 3], T[:, :3, 2], idx)


def sequence_places(path: str | Path, stride: int = 1, max_frames: int = 0) -> PlaceSet:
    """Frames of a real sequence that carry a ground-truth pose (TUM, KITTI, EuRoC readers)."""
    from vslam.data.registry import open_sequence

    seq = open_sequence(path)
    imgs, T, idx = [], [], []
    for k, fr in enumerate(seq):
        if max_frames and k >= max_frames:
            break
        if k % stride or fr.T_world_cam is None:
            continue
        imgs.append(fr.image)
        T.append(fr.T_world_cam)
        idx.append(fr.index)
    T = np.array(T).reshape(-1, 4, 4)
    return PlaceSet(Path(path).name, imgs, T[:, :3, 3], T[:, :3, 2], np.array(idx))
