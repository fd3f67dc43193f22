"""Where the learned keypoints' time goes, against ORB in the same run: ms per frame of SLAM's extractors at a
preset's settings, ALIKE step by step and layer by layer, and the guided matcher's ms per call.

Every frame runs through every method in turn (ORB, then ALIKE on each runtime), so a load that comes and goes
on a shared machine falls on all of them alike; the ratios to ORB are what to compare between runs. Medians over
``repeats`` passes of the frames after a warm-up.

Steps of one ALIKE frame (``alike.extract``'s laps): prep (colour, resize, tensor), network (the levels and the
score map), nms (mask, NMS maxima, top-k candidates), select (grid bucketing), refine (sub-pixel), describe (the
sparse descriptor head). Layers (torch only): the encoder's stem (two 3x3 convolutions at the network's full
resolution), the three residual blocks, the four 1x1 projections, the score map.

Guided matching (``matching.match_by_projection``, the per-frame matcher of SLAM tracking): the keypoints of
frame i-1 as the predictions into frame i at SLAM's radius, float descriptors (ALIKE) and binary (ORB).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from vslam.data.types import PinholeCamera
from vslam.features.base import FeatureConfig

LAYERS = ("stem", "enc2", "enc3", "enc4", "proj", "score")


@dataclass(frozen=True)
class SpeedSet:
    """Frames of one sequence and the settings to time them at: ``alike`` (a preset's ``slam.features``) and the
    ORB extractor at the same ``n_features``."""

    name: str
    images: list[np.ndarray]
    camera: PinholeCamera
    alike: FeatureConfig
    # further per-frame stages timed in the same loop, (name, fn(image, alike keypoints (N,2) pixels)); with any,
    # "front_end" is the first ALIKE runtime plus all of them, frame by frame (the learned front end's floor)
    extra: tuple[tuple[str, Callable[[np.ndarray, np.ndarray], Any]], ...] = ()


def layer_ms(model: torch.nn.Module, x: torch.Tensor) -> dict[str, float]:
    """ms of each of ``LAYERS`` for one (1,3,h,w) image through the torch network (``ALIKE.levels`` + score map,
    split at its layers)."""
    out: dict[str, float] = {}
    h, w = x.shape[-2:]
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        out[name] = out.get(name, 0.0) + 1e3 * (now - t)
        t = now

    from vslam.nn.keypoints.alike import PAD

    xp = F.pad(x, (0, -w % PAD, 0, -h % PAD))
    lap("stem")  # the padding counted with the stem
    x1 = model.stem(xp)
    lap("stem")
    x2 = model.enc2(F.max_pool2d(x1, 2))
    lap("enc2")
    x3 = model.enc3(F.max_pool2d(x2, 4))
    lap("enc3")
    x4 = model.enc4(F.max_pool2d(x3, 4))
    lap("enc4")
    levels = [F.relu(p(f)) for p, f in zip(model.proj, (x1, x2, x3, x4))]
    lap("proj")
    model.score_map(levels, (h, w))
    lap("score")
    return out


def _median(d: dict[str, list[float]]) -> dict[str, float]:
    return {k: statistics.median(v) for k, v in d.items()}


@torch.inference_mode()
def time_set(s: SpeedSet, repeats: int = 3, runtimes: tuple[str, ...] = ("torch", "onnxruntime"),
             radius_px: float = 15.0) -> dict[str, Any]:
    """-> {"ms": {method: median ms per frame}, "ratio": {method: ms / ORB's}, "ms_min": {method: fastest frame},
    "steps": {runtime: {step: ms}}, "layers": {layer: ms}, "keypoints": {method: mean count},
    "match_ms": {"float"|"binary": median ms per call}, "match_ms_min": {...: fastest call}, "matches": {...: mean
    pairs}, "size": "WxH", "frames": n}. ALIKE methods are named "<extractor> <runtime>". The minima are the cost
    with the least interference from other jobs; the medians what a frame took."""
    from vslam.features import make_extractor
    from vslam.features.alike import AlikeExtractor, extract, network_input
    from vslam.features.matching import match_by_projection

    cfg = s.alike
    orb = make_extractor(replace(cfg, extractor="orb"))
    alikes = {f"{cfg.extractor} {rt}": AlikeExtractor(replace(cfg, runtime=rt)) for rt in runtimes}
    ms: dict[str, list[float]] = {}
    steps: dict[str, dict[str, list[float]]] = {name: {} for name in alikes}
    layers: dict[str, list[float]] = {}
    counts: dict[str, list[int]] = {}
    feats: dict[str, list[Any]] = {"orb": [], "alike": []}

    for im in s.images[:2]:  # warm-up: allocations, onnxruntime's session, first-call paths
        orb.detect(im, s.camera)
        for ext in alikes.values():
            f = ext.detect(im, s.camera)
        for _, fn in s.extra:
            fn(im, f.raw)
    for rep in range(repeats):
        for im in s.images:
            t0 = time.perf_counter()
            f = orb.detect(im, s.camera)
            ms.setdefault("orb", []).append(1e3 * (time.perf_counter() - t0))
            counts.setdefault("orb", []).append(len(f))
            if rep == 0:
                feats["orb"].append(f)
            for name, ext in alikes.items():
                st = steps[name]
                t = t0 = time.perf_counter()

                def lap(step: str) -> None:
                    nonlocal t
                    now = time.perf_counter()
                    st.setdefault(step, []).append(1e3 * (now - t))
                    t = now

                xy, score, desc = extract(ext.model, im, cfg.n_features, ext.input_scale, None, ext.select,
                                          cfg.oversample, cfg.min_score, ext.maps, lap)
                ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
                counts.setdefault(name, []).append(len(xy))
                if name == next(iter(alikes)):
                    first_xy, first_ms = xy, ms[name][-1]
                    if rep == 0:
                        feats["alike"].append((s.camera.undistort_points(xy), desc))
            for name, fn in s.extra:
                t0 = time.perf_counter()
                fn(im, first_xy)
                ms.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
            if s.extra:
                ms.setdefault("front_end", []).append(first_ms + sum(ms[name][-1] for name, _ in s.extra))
            ext0 = next(iter(alikes.values()))
            x = network_input(im, ext0.input_scale)
            for k, v in layer_ms(ext0.model, x).items():
                layers.setdefault(k, []).append(v)

    # guided matching, frame i-1's keypoints predicted at their own pixels in frame i
    match_ms: dict[str, list[float]] = {}
    matches: dict[str, list[int]] = {}
    pairs = [("binary", (f.uv, f.desc)) for f in feats["orb"]], [("float", fd) for fd in feats["alike"]]
    for seqs in pairs:
        for (kind, (uv0, d0)), (_, (uv1, d1)) in zip(seqs[:-1], seqs[1:]):
            for _ in range(repeats):
                t0 = time.perf_counter()
                m = match_by_projection(uv0, d0, uv1, d1, radius_px)
                match_ms.setdefault(kind, []).append(1e3 * (time.perf_counter() - t0))
            matches.setdefault(kind, []).append(len(m))

    med = _median(ms)
    h, w = s.images[0].shape[:2]
    return {"ms": med, "ratio": {k: v / med["orb"] for k, v in med.items()}, "ms_min": {k: min(v) for k, v in ms.items()},
            "match_ms_min": {k: min(v) for k, v in match_ms.items()},
            "steps": {k: _median(v) for k, v in steps.items()}, "layers": _median(layers),
            "keypoints": {k: float(np.mean(v)) for k, v in counts.items()}, "match_ms": _median(match_ms),
            "matches": {k: float(np.mean(v)) for k, v in matches.items()}, "size": f"{w}x{h}",
            "frames": len(s.images), "n_features": cfg.n_features,
            "input_scale": next(iter(alikes.values())).input_scale}


def extraction_speed(sets: list[SpeedSet], repeats: int = 3, threads: int = 2,
                     runtimes: tuple[str, ...] = ("torch", "onnxruntime"),
                     progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """``time_set`` of every set on ``threads`` torch / OpenCV / onnxruntime threads -> {set name: result,
    "threads": threads}."""
    import cv2

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    out: dict[str, Any] = {"threads": threads}
    for i, s in enumerate(sets):
        out[s.name] = time_set(s, repeats, runtimes)
        if progress is not None:
            progress(i + 1, len(sets))
    return out


def format_table(res: dict[str, Any]) -> list[str]:
    """Markdown: per set, ms per frame and the ratio to ORB of each method; ALIKE's steps and layers (ms);
    guided matching ms per call."""
    sets = [k for k, v in res.items() if isinstance(v, dict) and "ms" in v]
    if not sets:
        return []
    methods = list(dict.fromkeys(m for s in sets for m in res[s]["ms"]))  # a set may time further stages
    lines = ["| set | size | n | " + " | ".join(f"{m} ms (x ORB; fastest)" for m in methods) +
             " | match ms float / binary (fastest) |",
             "|---|---|---|" + "---|" * (len(methods) + 1)]
    for s in sets:
        r = res[s]
        cells = [f"{r['ms'][m]:.1f} ({r['ratio'][m]:.2f}x; {r['ms_min'][m]:.1f})" if m in r["ms"] else "–"
                 for m in methods]
        mm, mn = r["match_ms"], r["match_ms_min"]
        nan = float("nan")
        lines.append(f"| {s} | {r['size']} @ {r['input_scale']:g} | {r['n_features']} | " + " | ".join(cells) +
                     f" | {mm.get('float', nan):.1f} / {mm.get('binary', nan):.1f} "
                     f"({mn.get('float', nan):.1f} / {mn.get('binary', nan):.1f}) |")
    steps = list(next(iter(res[sets[0]]["steps"].values())))
    lines += ["", "| set | runtime | " + " | ".join(steps) + " | layers: " + " | ".join(LAYERS) + " |",
              "|---|---|" + "---|" * (len(steps) + len(LAYERS))]
    for s in sets:
        r = res[s]
        for name, st in r["steps"].items():
            lay = " | ".join(f"{r['layers'][k]:.1f}" for k in LAYERS) if name.endswith("torch") else \
                " | ".join("–" for _ in LAYERS)
            lines.append(f"| {s} | {name} | " + " | ".join(f"{st[k]:.1f}" for k in steps) + f" | {lay} |")
    return lines
