"""ConvPoint: a light SuperPoint-style keypoint detector + descriptor (seed 003 replaces ORB with it).

One shared encoder at 1/8 resolution (a stride-2 first layer: SuperPoint's full-resolution 3x3 layers cost
several times this encoder on the CPU; docs/features.md, 'Measurements behind settings in the code'), two
heads:

* keypoints: 65 channels per 8x8 cell (64 pixel positions + "no keypoint"), softmax, depth-to-space -> a
  full-resolution heatmap (DeTone et al., "SuperPoint", CVPR-W 2018);
* descriptors: ``desc_dim`` channels at 1/8 resolution, sampled bilinearly at the keypoints, L2-normalised.

The input is a grey image standardised per image (mean 0, std 1), so a global gain or offset of the exposure
changes nothing before the first layer. Only torch, numpy and cv2 are imported here (the GPU machine has no
gtsam / pycolmap), so training and the network also run there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from vslam.resources import shipped_model

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ConvPointConfig:
    channels: tuple[int, ...] = (24, 48, 96, 128)  # encoder widths at 1/2, 1/4, 1/8, 1/8
    desc_dim: int = 128


def _cbr(i: int, o: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)]


class ConvPointNet(nn.Module):
    """(B,1,H,W) grey in [0,1], H and W multiples of 8 -> (logits (B,65,H/8,W/8), desc (B,D,H/8,W/8) unit)."""

    def __init__(self, cfg: ConvPointConfig = ConvPointConfig()):
        super().__init__()
        self.cfg = cfg
        c1, c2, c3, c4 = cfg.channels
        self.encoder = nn.Sequential(*_cbr(1, c1, 2), *_cbr(c1, c1), *_cbr(c1, c2, 2), *_cbr(c2, c2),
                                     *_cbr(c2, c3, 2), *_cbr(c3, c3), *_cbr(c3, c4))
        self.det = nn.Sequential(*_cbr(c4, c4), nn.Conv2d(c4, 65, 1))
        self.desc = nn.Sequential(*_cbr(c4, c4), nn.Conv2d(c4, cfg.desc_dim, 1))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.encoder(standardize(x))
        return self.det(f), F.normalize(self.desc(f), dim=1)


def standardize(x: torch.Tensor) -> torch.Tensor:
    """(B,1,H,W) grey -> mean 0, std 1 per image (a global gain or offset of the exposure changes nothing)."""
    mu = x.mean(dim=(2, 3), keepdim=True)
    sd = x.std(dim=(2, 3), keepdim=True).clamp_min(1e-3)
    return (x - mu) / sd


class _Core(nn.Module):
    """Encoder + both heads on a standardised image: the part ``vslam.quantize`` turns into int8."""

    def __init__(self, net: ConvPointNet):
        super().__init__()
        self.encoder, self.det, self.desc = net.encoder, net.det, net.desc

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.encoder(x)
        return self.det(f), self.desc(f)


#: Layers the int8 network keeps in float: the first convolution (+ BN, ReLU) sees the standardised image itself.
#: Kept in float, the int8 network stays closer to the float one on held-out homography pairs, at the same
#: speed (docs/features.md).
INT8_FLOAT_MODULES = ("encoder.0", "encoder.1", "encoder.2")
INT8_COMMAND = "vslam quantize keypoints"


class ConvPointInt8(nn.Module):
    """``ConvPointNet``'s forward with the encoder and heads as an int8 graph (CPU only, ``vslam.quantize``)."""

    def __init__(self, core: nn.Module, cfg: ConvPointConfig):
        super().__init__()
        self.core, self.cfg = core, cfg

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, desc = self.core(standardize(x).contiguous(memory_format=torch.channels_last))
        return logits, F.normalize(desc, dim=1)


def int8_convpoint(net: ConvPointNet, qparams: dict[str, float]) -> ConvPointInt8:
    from vslam.quantize import build

    core = build(_Core(net).eval(), qparams, INT8_FLOAT_MODULES, torch.zeros(1, 1, 64, 64))
    return ConvPointInt8(core, net.cfg).eval()


def heatmap(logits: torch.Tensor) -> torch.Tensor:
    """(B,65,Hc,Wc) cell logits -> (B,H,W) keypoint probability per pixel (the dustbin dropped)."""
    return F.pixel_shuffle(logits.softmax(dim=1)[:, :64], 8)[:, 0]


def _window_max(x: torch.Tensor, radius: int) -> torch.Tensor:
    """(B,H,W) max over each (2r+1)^2 window (outside the image counts as -inf). On the CPU OpenCV's dilation
    (much faster than torch's max-pool there; docs/features.md, 'Measurements behind settings in the code');
    on a GPU torch's max-pool."""
    k = 2 * radius + 1
    if x.device.type == "cpu":
        kern = np.ones((k, k), np.uint8)
        return torch.from_numpy(np.stack([cv2.dilate(np.ascontiguousarray(v), kern) for v in x.float().numpy()])).to(x.dtype)
    return F.max_pool2d(x[:, None], k, stride=1, padding=radius)[:, 0]


def nms(heat: torch.Tensor, radius: int) -> torch.Tensor:
    """(B,H,W) -> the heat where it is the maximum of its (2r+1)^2 window, else 0.

    Pixels tied within a window (flat plateaus) would all pass a plain max test; of those the first in
    row-major order is kept, so the result is deterministic and no two survivors lie within ``radius``
    (Chebyshev) of each other.
    """
    if radius <= 0:
        return heat
    b, h, w = heat.shape
    peak = (heat == _window_max(heat, radius)) & (heat > 0)
    # peaks sharing a window are equal (each is >= the other): keep the one with the smallest index
    neg_idx = -torch.arange(h * w, dtype=torch.float32, device=heat.device).view(1, h, w).expand(b, h, w)
    key = torch.where(peak, neg_idx, torch.full_like(neg_idx, -float(h * w + 1)))
    first = key == _window_max(key, radius)
    return torch.where(peak & first, heat, torch.zeros_like(heat))


def sample_descriptors(desc: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of a (B,D,Hc,Wc) coarse map at (B,N,2) full-resolution pixel centres -> (B,N,D) unit.

    Cell (i, j) describes the 8x8 block whose centre is pixel (8j + 3.5, 8i + 3.5)."""
    b, d, hc, wc = desc.shape
    gx = (xy[..., 0] - 3.5) / 8.0 / max(wc - 1, 1) * 2 - 1
    gy = (xy[..., 1] - 3.5) / 8.0 / max(hc - 1, 1) * 2 - 1
    g = torch.stack([gx, gy], dim=-1)[:, :, None]  # (B,N,1,2)
    s = F.grid_sample(desc, g, mode="bilinear", align_corners=True, padding_mode="border")[..., 0]
    return F.normalize(s.transpose(1, 2), dim=2)


def subpixel(heat: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Keypoints moved to the heat-weighted centroid of their 3x3 neighbourhood (a soft-argmax)."""
    h, w = heat.shape
    x, y = xy[:, 0].astype(np.int64), xy[:, 1].astype(np.int64)
    off = np.arange(-1, 2)
    xs = np.clip(x[:, None, None] + off[None, None, :], 0, w - 1)
    ys = np.clip(y[:, None, None] + off[None, :, None], 0, h - 1)
    p = heat[ys, xs]  # (N,3,3)
    s = np.maximum(p.sum(axis=(1, 2)), 1e-12)
    dx = (p * off[None, None, :]).sum(axis=(1, 2)) / s
    dy = (p * off[None, :, None]).sum(axis=(1, 2)) / s
    return np.stack([x + dx, y + dy], axis=1)


def to_gray(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def batch_tensor(images: list[np.ndarray]) -> tuple[torch.Tensor, tuple[int, int]]:
    """Grey uint8 images of one size -> (B,1,H8,W8) float in [0,1] padded (edge-replicated) to multiples of 8."""
    h, w = images[0].shape[:2]
    ph, pw = (-h) % 8, (-w) % 8
    arr = np.stack([cv2.copyMakeBorder(to_gray(im), 0, ph, 0, pw, cv2.BORDER_REPLICATE) for im in images])
    return torch.from_numpy(arr).float().div_(255.0)[:, None], (h, w)


@dataclass(frozen=True)
class DetectSettings:
    """Inference settings. ``border``: pixels at the image edge without keypoints (the padded cells there
    see replicated pixels)."""

    conf_thresh: float = 0.005
    nms_radius: int = 4
    max_keypoints: int = 1500
    border: int = 8
    subpixel: bool = True
    bf16: bool = False  # network in bfloat16 autocast (CPUs with AVX512-BF16, GPUs): faster, not bit-identical


@torch.inference_mode()
def detect_batch(model: ConvPointNet, images: list[np.ndarray], s: DetectSettings, device: torch.device | None = None,
                 masks: list[np.ndarray | None] | None = None, select=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Keypoints of same-size images in one forward pass -> per image (xy (N,2) float64 pixels, score (N,),
    desc (N,D) float32 unit). ``masks``: True where keypoints are not wanted. ``select(xy, score, shape)`` ->
    indices of the keypoints to keep among the NMS survivors (default: the ``max_keypoints`` strongest)."""
    dev = device or next(model.parameters(), torch.empty(0)).device
    x, (h, w) = batch_tensor(images)
    x = x.to(dev).contiguous(memory_format=torch.channels_last)  # NHWC: faster convolutions on the CPU
    with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=s.bf16 and not isinstance(model, ConvPointInt8)):
        logits, desc = model(x)
    logits, desc = logits.float(), desc.float()  # sample_descriptors re-normalises what it samples
    heat = heatmap(logits)[:, :h, :w]
    peaks = nms(heat, s.nms_radius).cpu().numpy()
    heat_np = heat.cpu().numpy()
    out = []
    for b in range(len(images)):
        p = peaks[b]
        if s.border > 0:
            p[:s.border] = p[-s.border:] = 0
            p[:, :s.border] = p[:, -s.border:] = 0
        if masks is not None and masks[b] is not None:
            p[masks[b][:h, :w]] = 0
        ys, xs = np.nonzero(p >= s.conf_thresh)
        score = p[ys, xs].astype(np.float64)
        xy = np.stack([xs, ys], axis=1).astype(np.float64)
        if select is not None:
            keep = select(xy, score, (h, w))
        else:
            keep = np.lexsort((np.arange(len(score)), -score))[: s.max_keypoints]
        xy, score = xy[keep], score[keep]
        if s.subpixel and len(xy):
            xy = subpixel(heat_np[b], xy)
        d = sample_descriptors(desc[b:b + 1], torch.from_numpy(xy).float().to(dev)[None])[0]
        out.append((xy, score, d.cpu().numpy().astype(np.float32)))
    return out


def save_convpoint(model: ConvPointNet, path: str | Path, meta: dict | None = None) -> Path:
    from vslam.nn.checkpoint import save_weights

    return save_weights(model, {"channels": list(model.cfg.channels), "desc_dim": model.cfg.desc_dim}, path, meta)


def load_convpoint(path: str | Path, int8: bool = False) -> ConvPointNet | ConvPointInt8:
    """Weights from a local file (never the network); eval mode, CPU, NHWC (the layout detect_batch feeds).
    ``int8``: the quantised network with the ranges stored beside the weights (``vslam quantize keypoints``)."""
    model = _read_weights(path)
    return _int8_from_file(model, path) if int8 else model.to(memory_format=torch.channels_last)


def _read_weights(path: str | Path) -> ConvPointNet:
    """The float network of a weights file, in the layout it was saved in (quantised from that layout)."""
    from vslam.nn.checkpoint import load_weights

    return load_weights(path, "ConvPoint", "vslam train keypoints", lambda c: ConvPointNet(
        ConvPointConfig(tuple(int(v) for v in c["channels"]), int(c["desc_dim"]))), _looks_like)


def _looks_like(state: Mapping[str, Any]) -> str:
    """What a ConvPoint state dict's tensors were made for: its encoder channels and descriptor size."""
    enc = [int(v.shape[0]) for k, v in state.items() if k.startswith("encoder.") and getattr(v, "ndim", 0) == 4]
    desc = [int(v.shape[0]) for k, v in state.items() if k.startswith("desc.") and getattr(v, "ndim", 0) == 4]
    if len(enc) != 7 or len(desc) != 2:
        return ""
    return f"its tensors are a ConvPoint of channels {enc[::2]}, desc_dim {desc[-1]}"


def _int8_from_file(net: ConvPointNet, path: str | Path) -> ConvPointInt8:
    from vslam.quantize import load_qparams

    return int8_convpoint(net, load_qparams(path, INT8_COMMAND)[0])


def _load_extractor_model(path: str | Path, int8: bool) -> ConvPointNet | ConvPointInt8:
    """The int8 network when asked and its ranges fit the weights, else (one warning why) the float one: weights
    trained here without `vslam quantize keypoints` still run, only slower. Weights that cannot be read are an
    error either way."""
    from vslam.errors import ConfigError

    model = _read_weights(path)
    if int8:
        try:
            return _int8_from_file(model, path)  # ``build`` quantises a copy: ``model`` stays float
        except ConfigError as e:
            log.warning("features.int8: %s; running the float network", e)
    return model.to(memory_format=torch.channels_last)


def default_weights() -> Path:
    """The shipped weights (package data vslam/models/convpoint_v1.pt, int8 ranges beside them)."""
    return shipped_model("convpoint_v1.pt")


class ConvPointExtractor:
    """The ``Extractor`` of SLAM configs with ``features.extractor: convpoint``: one forward pass per image
    (or per stereo pair, ``detect_many``), NMS, keypoints spread over the grid like ORB's (``orb.bucket``),
    128-d float descriptors (matched by L2, ``features.matching``)."""

    descriptor_kind = "float"

    def __init__(self, cfg):
        from vslam.nn.device import pick_device

        self.cfg = cfg
        self.device = pick_device(cfg.device, "features.device")
        # integer kernels are CPU-only: on CUDA the float network runs (bf16 if asked)
        self.model = _load_extractor_model(cfg.weights or default_weights(), cfg.int8 and self.device.type == "cpu")
        self.model.to(self.device)
        self.settings = DetectSettings(conf_thresh=cfg.conf_thresh, nms_radius=cfg.nms_radius,
                                       max_keypoints=cfg.n_features, bf16=cfg.bf16)

    def _select(self, xy: np.ndarray, score: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        from vslam.features.orb import bucket

        return bucket(xy, score, shape, self.cfg.n_features, self.cfg.grid_cols, self.cfg.grid_rows)

    def detect_many(self, images: list[np.ndarray], cameras: list, masks: list | None = None) -> list:
        """Features of same-size images in one batch (a stereo pair)."""
        from vslam.features.base import Features

        res = detect_batch(self.model, images, self.settings, self.device, masks, self._select)
        return [Features(raw=xy, uv=cam.undistort_points(xy), desc=d, octave=np.zeros(len(xy), np.int64),
                         response=score, scale_factor=self.cfg.scale_factor)
                for (xy, score, d), cam in zip(res, cameras)]

    def detect(self, image: np.ndarray, camera, mask: np.ndarray | None = None):
        return self.detect_many([image], [camera], None if mask is None else [mask])[0]
