"""ALIKE keypoints for SLAM and the benchmarks: ``extract`` (one image -> keypoints, scores, descriptors) and the
``Extractor`` of configs with ``features.extractor: alike-t | alike-s | alike-n``.

The network (``vslam.nn.keypoints.alike``) runs on the image resized by ``features.input_scale`` (half resolution
costs a quarter and keeps most of the two-view accuracy: docs/features.md); candidates are the NMS maxima, the
``n`` kept ones are chosen before any descriptor is computed (the grid bucketing of ORB for SLAM, the strongest
for the benchmarks), and only those are refined to sub-pixel and described (the sparse head). Weights: the
shipped ``vslam/models/alike_<variant>.pt`` (the public BSD-3-Clause checkpoints converted to our layout, float16),
or a ``save_model`` file given as ``features.weights``; nothing is downloaded.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from vslam.data.types import PinholeCamera
from vslam.features.base import FeatureConfig, Features

VARIANTS = ("alike-t", "alike-s", "alike-n")
Select = Callable[[np.ndarray, np.ndarray, tuple[int, int]], np.ndarray]
# (1,3,h,w) image, (h, w) -> (the four levels, the (h,w) score map): ALIKE.levels + score_map, or onnxruntime's
Maps = Callable[[torch.Tensor, tuple[int, int]], tuple[list[torch.Tensor], torch.Tensor]]
RUNTIMES = ("torch", "onnxruntime")


def shipped_weights(name: str) -> Path:
    """The package-data file of ``name`` (alike-t -> vslam/models/alike_t.pt)."""
    from vslam.resources import shipped_model

    return shipped_model(name.replace("-", "_") + ".pt")


def load_alike(name: str, weights: str | Path = "") -> torch.nn.Module:
    """The network ``name`` with the weights of ``weights`` (a ``save_model`` file) or the shipped file; eval, CPU.
    A file of another variant than ``name`` is one ConfigError line naming both."""
    from vslam.errors import ConfigError
    from vslam.nn.checkpoint import load_model
    from vslam.nn.registry import KEYPOINTS

    path = Path(weights) if weights else shipped_weights(name)
    model, ck = load_model(path, KEYPOINTS, "features.weights")
    if ck["arch"] != name:
        raise ConfigError(f"{path}: an {ck['arch']} checkpoint, but features.extractor is {name}")
    # BatchNorm folded into the convolutions and NHWC layout: inference only, faster on the CPU than NCHW with BN
    # (docs/features.md)
    return model.fused().to(memory_format=torch.channels_last)


def torch_maps(model: torch.nn.Module) -> Maps:
    """``Maps`` of the network itself (torch)."""
    def maps(x: torch.Tensor, hw: tuple[int, int]) -> tuple[list[torch.Tensor], torch.Tensor]:
        levels = model.levels(x)
        return levels, model.score_map(levels, hw)[0, 0]

    return maps


def make_maps(model: torch.nn.Module, runtime: str) -> Maps:
    """The dense part of ``model`` run by ``runtime`` (``RUNTIMES``): torch, or onnxruntime
    (``vslam.nn.keypoints.alike_onnx``; the same maps to float rounding, faster on a loaded 2-core machine)."""
    from vslam.errors import ConfigError

    if runtime == "torch":
        return torch_maps(model)
    if runtime == "onnxruntime":
        from vslam.nn.keypoints.alike_onnx import OnnxMaps

        return OnnxMaps(model)
    raise ConfigError(f"slam.features.runtime: unknown {runtime!r} (known: {', '.join(RUNTIMES)})")


def to_rgb(image: np.ndarray) -> np.ndarray:
    """BGR (OpenCV's order, as the readers give) or grey -> RGB, the published network's input."""
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def network_input(image: np.ndarray, scale: float = 1.0) -> torch.Tensor:
    """uint8 (H,W,3) BGR or (H,W) grey -> the network's (1,3,h,w) float32 RGB in [0,1], h, w = H, W x ``scale``
    (area interpolation), channels-last. Built in numpy (one thread): a view of an (h,w,3) array is already
    channels-last, and torch's own ops would start its thread team for a few hundred kilobytes."""
    h0, w0 = image.shape[:2]
    rgb = to_rgb(image)
    if scale != 1.0:
        rgb = cv2.resize(rgb, (max(1, round(w0 * scale)), max(1, round(h0 * scale))), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.divide(rgb, np.float32(255.0), dtype=np.float32)).permute(2, 0, 1)[None]


@torch.inference_mode()
def extract(model: torch.nn.Module, image: np.ndarray, n: int, scale: float = 1.0, mask: np.ndarray | None = None,
            select: Select | None = None, oversample: float = 3.0, min_score: float = 0.0, maps: Maps | None = None,
            lap: Callable[[str], None] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints of one uint8 image (H,W,3) BGR or (H,W) grey -> (xy (N,2) float64 pixels of ``image``, score (N,)
    float64, desc (N,D) float32 unit), N <= n.

    ``scale``: the network sees the image resized by it (area interpolation); ``mask`` (H,W) bool: True where
    keypoints are not wanted; ``select(xy, score, shape)`` -> indices to keep among ``oversample * n`` candidates
    (xy in network pixels, shape the network image's (h, w)); without it, the ``n`` strongest by descending score.
    ``min_score``: only maxima scoring above it are keypoints (the benchmarks keep every maximum; SLAM does not).
    ``maps``: what computes the levels and the score map (``make_maps``); None: ``model`` in torch.
    ``lap(step)``: called as each step ends (prep, network, nms, select, refine, describe): the speed bench's timer.
    """
    lap = lap or (lambda step: None)
    h0, w0 = image.shape[:2]
    x = network_input(image, scale)
    h, w = x.shape[-2:]
    lap("prep")
    levels, smap = (maps or torch_maps(model))(x, (h, w))
    lap("network")
    if mask is not None:
        small = mask if (h, w) == (h0, w0) else cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        smap = smap.masked_fill(torch.from_numpy(small), 0.0)  # a masked pixel is never a maximum above zero
    k = n if select is None else max(n, int(round(oversample * n)))
    idx, val = model.candidates(smap, k)
    keep_nz = val > max(min_score, 0.0)  # top-k on a sparse map also returns zeros: not keypoints
    idx, val = idx[keep_nz], val[keep_nz]
    lap("nms")
    if select is not None and len(idx) > n:
        xy_int = torch.stack([idx % w, idx // w], 1).numpy().astype(np.float64)
        pick = torch.from_numpy(np.asarray(select(xy_int, val.numpy().astype(np.float64), (h, w)), np.int64))
        idx = idx[pick]
    else:
        idx = idx[:n]
    lap("select")
    xy, score = model.refine(smap, idx)
    lap("refine")
    desc = model.describe(levels, xy, (h, w))
    lap("describe")
    xy_np = xy.numpy().astype(np.float64)
    if (h, w) != (h0, w0):  # pixel centres: x_full + 0.5 = (x + 0.5) * w0 / w
        xy_np = (xy_np + 0.5) * np.array([w0 / w, h0 / h]) - 0.5
    order = np.argsort(-score.numpy(), kind="stable") if select is None else np.arange(len(xy_np))
    return xy_np[order], score.numpy().astype(np.float64)[order], desc.numpy().astype(np.float32)[order]


# the input scale of a config that names ALIKE without one: SLAM's accuracy at half resolution is ORB's or
# better at a quarter of the network's cost (docs/features.md); the learned presets use it too
DEFAULT_INPUT_SCALE = 0.5


class AlikeExtractor:
    """The ``Extractor`` of ``features.extractor: alike-*``: at most ``n_features`` keypoints scoring above
    ``min_score``, spread over the ``grid_cols`` x ``grid_rows`` grid like ORB's (``orb.bucket``), float
    descriptors matched by L2 (``features.matching``). The floor matters: the grid otherwise fills plain cells with
    weak, poorly placed maxima, and SLAM's accuracy falls as they are added (docs/features.md). The network runs on
    the CPU (``features.device`` is ConvPoint's); it is small enough that a GPU was never measured for it. Its dense
    part runs in torch or onnxruntime (``features.runtime``)."""

    descriptor_kind = "float"

    def __init__(self, cfg: FeatureConfig):
        self.cfg = cfg
        self.input_scale = DEFAULT_INPUT_SCALE if cfg.input_scale is None else cfg.input_scale
        self.model = load_alike(cfg.extractor, cfg.weights)
        self.maps = make_maps(self.model, cfg.runtime)

    def select(self, xy: np.ndarray, score: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        from vslam.features.orb import bucket

        return bucket(xy, score, shape, self.cfg.n_features, self.cfg.grid_cols, self.cfg.grid_rows)

    def detect(self, image: np.ndarray, camera: PinholeCamera, mask: np.ndarray | None = None) -> Features:
        xy, score, desc = extract(self.model, image, self.cfg.n_features, self.input_scale, mask, self.select,
                                  self.cfg.oversample, self.cfg.min_score, self.maps)
        return Features(raw=xy, uv=camera.undistort_points(xy), desc=desc, octave=np.zeros(len(xy), np.int64),
                        response=score, scale_factor=self.cfg.scale_factor)
