"""Place-retrieval evaluation: recall@k of a place descriptor on database / query sets (the
``place-recognition`` bench row).

A query counts when the database holds at least one frame of the same place (``place_data.same_place``); it
is recalled at k when one of its k most similar database frames (cosine = dot of unit descriptors) is such a
frame. Within one sequence, frames closer than ``exclude_frames`` in time are left out of each other's ranking
(they are trivially similar and the loop closer never asks for them either). Every descriptor is fed its
native input: the BoW baseline the tracker's ORB keypoints of the full image, VLADNet the image.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from vslam.train.place_data import PlaceSet, same_place, sequence_places, synthetic_route

Describer = Callable[[list], np.ndarray]  # images -> (N,D) unit descriptors


def bow_describer(n_features: int = 1000) -> Describer:
    """The loop closer's BoW descriptor on the SLAM front end's ORB keypoints (vslam/models/orb_bow_k512.npz)."""
    from vslam.data.types import PinholeCamera
    from vslam.features import FeatureConfig, make_extractor
    from vslam.loop.descriptor import make_place_descriptor

    ext = make_extractor(FeatureConfig(n_features=n_features))
    bow = make_place_descriptor("bow")

    def run(images: list) -> np.ndarray:
        out = []
        for im in images:
            h, w = im.shape[:2]
            cam = PinholeCamera(w, h, float(w), float(w), (w - 1) / 2, (h - 1) / 2)
            out.append(bow.describe(im, ext.detect(im, cam)))
        return np.array(out, dtype=np.float32)

    return run


def vladnet_describer(path: str) -> Describer:
    from vslam.loop.vladnet import VladNetDescriptor

    d = VladNetDescriptor.from_file(path)
    return d.describe_many


def recall_at(desc_db: np.ndarray, desc_q: np.ndarray, positives: np.ndarray, ks: tuple[int, ...] = (1, 5, 10),
              excluded: np.ndarray | None = None) -> dict[str, float]:
    """positives (Q,N) bool; excluded (Q,N) bool pairs never ranked. -> recall@k per k, queries counted."""
    sim = desc_q @ desc_db.T
    if excluded is not None:
        sim = np.where(excluded, -np.inf, sim)
        positives = positives & ~excluded
    has = positives.any(axis=1)
    order = np.argsort(-sim, axis=1, kind="stable")
    out: dict[str, float] = {"queries": int(has.sum())}
    for k in ks:
        hit = np.take_along_axis(positives, order[:, :k], axis=1).any(axis=1)
        out[f"r@{k}"] = float(hit[has].mean()) if has.any() else float("nan")
    return out


def evaluate_retrieval(describers: dict[str, Describer], places: PlaceSet, db_rows: np.ndarray, query_rows: np.ndarray,
                       pos_m: float, pos_deg: float, exclude_frames: int = 0,
                       ks: tuple[int, ...] = (1, 5, 10)) -> dict[str, dict]:
    """recall@k of each describer for the queries ``places[query_rows]`` against the database ``places[db_rows]``
    (each image described once, also when it is in both). exclude_frames > 0: pairs closer than that many frames
    are never ranked (a frame never finds itself or its neighbours)."""
    db, q = places.subset(db_rows), places.subset(query_rows)
    pos = same_place(q, db, pos_m, pos_deg)
    excl = np.abs(q.index[:, None] - db.index[None]) < exclude_frames if exclude_frames > 0 else None
    out = {}
    for name, fn in describers.items():
        t0 = time.perf_counter()
        d = fn(places.images)
        ms = (time.perf_counter() - t0) * 1e3 / len(places)
        out[name] = {**recall_at(d[db_rows], d[query_rows], pos, ks, excl), "ms_per_image": ms, "dim": int(d.shape[1])}
    return out


@dataclass(frozen=True)
class HeldOut:
    """One evaluation set: queries (rows of ``places``) against a database (rows), what counts as the same place,
    its table label."""

    label: str
    places: PlaceSet
    db_rows: np.ndarray
    query_rows: np.ndarray
    pos_m: float
    pos_deg: float
    exclude_frames: int = 0


def held_out_sets(seed: int = 0, frames: int = 600, size: tuple[int, int] = (320, 240), stride: int = 3,
                  speed: float = 1.4, pos_m: float = 0.5, pos_deg: float = 30.0, tum: Path | None = None,
                  tum_split: int = 100, tum_pos_m: float = 0.3, tum_exclude_frames: int = 30) -> dict[str, HeldOut]:
    """The sets VLADNet never trained on, shared by its trainer and ``vslam bench``: "synthetic" -- the second half
    of the 2-lap looping route ``seed`` (lighting change on) against its first half; "tum" (when ``tum`` exists) --
    frames from ``tum_split`` on against every frame at least ``tum_exclude_frames`` away."""
    r = synthetic_route(seed, frames, size, stride, speed=speed)
    half = len(r) // 2
    out = {"synthetic": HeldOut(f"synthetic room seed {seed}, 2 laps, lighting change: lap 2 vs lap 1 "
                                f"(≤ {pos_m:g} m, ≤ {pos_deg:g}°)", r, np.arange(half), np.arange(half, len(r)), pos_m, pos_deg)}
    if tum is not None and Path(tum).exists():
        t = sequence_places(tum)
        out["tum"] = HeldOut(f"TUM fr3/teddy, frames ≥ {tum_split} (not trained on) vs every frame ≥ {tum_exclude_frames} "
                             f"apart (≤ {tum_pos_m:g} m, ≤ {pos_deg:g}°)", t, np.arange(len(t)),
                             np.flatnonzero(t.index >= tum_split), tum_pos_m, pos_deg, tum_exclude_frames)
    return out


def evaluate_held_out(describers: dict[str, Describer], sets: dict[str, HeldOut]) -> dict[str, dict]:
    """``evaluate_retrieval`` on each of ``held_out_sets``, keyed like them."""
    return {k: evaluate_retrieval(describers, h.places, h.db_rows, h.query_rows, h.pos_m, h.pos_deg, h.exclude_frames)
            for k, h in sets.items()}


def database_costs(dim: int, n: int = 10_000, seed: int = 0, repeats: int = 20) -> dict[str, float]:
    """Memory per keyframe (float32 vector) and the time of one query (matrix product + top-10) over ``n``
    random unit vectors: what the keyframe database costs at 10k keyframes."""
    rng = np.random.default_rng(seed)
    db = rng.normal(size=(n, dim)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q = db[rng.integers(n)]
    t0 = time.perf_counter()
    for _ in range(repeats):
        s = db @ q
        np.argpartition(-s, 10)[:10]
    return {"keyframes": n, "bytes_per_keyframe": dim * 4, "query_ms": (time.perf_counter() - t0) * 1e3 / repeats}
