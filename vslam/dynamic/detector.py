"""Inference wrapper around the YOLOv8-like detector: image in, boxes out (numpy at the boundary).

Imports only torch, numpy and cv2, so it loads without the SLAM back end (gtsam, pycolmap).
A checkpoint is a ``torch.save`` dict: ``model`` (state dict), ``config`` (DetectorConfig fields), ``names``
(class names, index = class id) and, for training checkpoints, optimiser state and progress.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from vslam.dynamic.detections import Detections, postprocess  # noqa: F401 (the names callers import from here)
from vslam.dynamic.model import SCALES, DetectorConfig, YoloDetector, decode, fuse_for_inference, mask_outputs
from vslam.errors import ConfigError
from vslam.resources import shipped_model


def letterbox(image: np.ndarray, size: int) -> tuple[np.ndarray, float, tuple[int, int]]:
    """Resize the longer side to ``size`` keeping aspect, pad to a multiple of 32 (grey 114, the YOLO habit).
    -> padded image, scale (new / old), (pad_x, pad_y) added on the left/top."""
    h, w = image.shape[:2]
    r = size / max(h, w)
    nh, nw = round(h * r), round(w * r)
    im = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR) if (nh, nw) != (h, w) else image
    ph, pw = (-nh) % 32, (-nw) % 32
    top, left = ph // 2, pw // 2
    im = cv2.copyMakeBorder(im, top, ph - top, left, pw - left, cv2.BORDER_CONSTANT, value=(114, 114, 114))
    return im, r, (left, top)


def to_tensor(images_rgb: list[np.ndarray], device: torch.device | None = None) -> torch.Tensor:
    """List of (H,W,3) uint8 RGB, same size -> (B,3,H,W) float32 in [0,1] on ``device`` (default the CPU). The
    uint8 pixels go to the device first (a quarter of the bytes over the bus) and are scaled there."""
    return torch.from_numpy(np.stack(images_rgb)).to(device or "cpu").permute(0, 3, 1, 2).float().div_(255.0)


@torch.no_grad()
def instance_masks(coef: torch.Tensor, proto: torch.Tensor, boxes: torch.Tensor, pad: tuple[int, int], r: float,
                   shape: tuple[int, int]) -> np.ndarray:
    """Kept detections' masks in the original image: coef (K, nm), proto (nm, h, w) of the letterboxed input,
    boxes (K, 4) letterbox pixels, ``pad``/``r`` the letterbox's, ``shape`` (H, W) -> (K, H, W) bool, cut at 0.5
    probability after bilinear resizing to the letterbox, then its unpadded window to the image."""
    from vslam.dynamic.model import assemble_masks

    H, W = shape
    if len(coef) == 0:
        return np.zeros((0, H, W), bool)
    logits = assemble_masks(coef, proto, boxes)[None].float()
    h, w = logits.shape[2:]
    full = F.interpolate(logits, size=(4 * h, 4 * w), mode="bilinear", align_corners=False)  # letterbox pixels
    px, py = pad
    window = full[..., py:py + round(H * r), px:px + round(W * r)]
    up = F.interpolate(window, size=(H, W), mode="bilinear", align_corners=False)[0]
    return (up > 0).cpu().numpy()


class Detector:
    """``detect(image)``: BGR or grey uint8 image -> Detections in that image's pixels. Runs a fused copy of
    ``model`` (``fuse_for_inference``) on ``device``; the model passed in is left as it was. On CUDA the network,
    box decoding and NMS stay on the GPU: one small copy of the kept boxes comes back."""

    def __init__(self, model: YoloDetector, names: list[str], img_size: int = 640, conf: float = 0.25, iou: float = 0.6,
                 device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self.model, self.names = fuse_for_inference(model).to(self.device), list(names)
        self.img_size, self.conf, self.iou = img_size, conf, iou

    def detect(self, image: np.ndarray) -> Detections:
        rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB if image.ndim == 2 else cv2.COLOR_BGR2RGB)
        im, r, (px, py) = letterbox(rgb, self.img_size)
        masks = None
        with torch.inference_mode():
            feats = self.model(to_tensor([im], self.device))
            boxes, probs = decode(self.model, feats)
            if self.model.cfg.masks:
                coef, proto = mask_outputs(self.model, feats)
                bt, s, c, k = postprocess(boxes, probs, self.conf, self.iou, extra=coef)[0]
                masks = instance_masks(k, proto[0], bt, (px, py), r, image.shape[:2])
            else:
                bt, s, c = postprocess(boxes, probs, self.conf, self.iou)[0]
        b = bt.cpu().numpy().astype(np.float64)
        b[:, [0, 2]] = (b[:, [0, 2]] - px) / r
        b[:, [1, 3]] = (b[:, [1, 3]] - py) / r
        ids = c.cpu().numpy().astype(np.int64)
        return Detections(b, s.cpu().numpy().astype(np.float64), ids, np.array([self.names[i] for i in ids], dtype=object),
                          masks, 4.0 / r if masks is not None else 0.0)


def save_checkpoint(path: str | Path, model: YoloDetector, names: list[str], half: bool = False, **extra: object) -> Path:
    """``half``: float tensors stored as float16 (a YOLOv8n is 12 MB in float32, 6 MB in float16; loading casts
    back to float32, outputs change by ~1e-3 of a score)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(p.suffix + ".tmp")
    state = {k: v.half() if half and v.is_floating_point() else v for k, v in model.state_dict().items()}
    torch.save({"model": state, "config": asdict(model.cfg), "names": list(names), **extra}, tmp)
    tmp.replace(p)  # atomic: an interrupted save never leaves a broken checkpoint behind
    return p


def default_weights() -> Path:
    """The shipped detector (package data vslam/models/detector_se_seg.pt: the SE detector with an instance-mask
    head; its card, and why this one, in models/README.md)."""
    return shipped_model("detector_se_seg.pt")


def photo_weights() -> Path:
    """The detector ``vslam detect`` uses by default: the public YOLOX-nano converted to our network
    (vslam/models/yolox_nano_slam.pt), far ahead of ``default_weights`` on real photos but behind it in SLAM,
    where it also boxes static people-like objects and parked cars (models/README.md; docs/detector-data.md,
    'Measurements behind settings in the code')."""
    return shipped_model("yolox_nano_slam.pt")


def load_model(path: str | Path, field: str = "slam.dynamic.weights") -> tuple[YoloDetector, dict]:
    """``field``: the config field that named ``path``, for the error when it is missing."""
    from vslam.nn.checkpoint import load_state, read_checkpoint, reading

    if not Path(path).is_file():
        raise ConfigError(f"{path}: detector weights not found ({field})")
    what = "detector checkpoint"
    ckpt = read_checkpoint(path, what, ("model", "config", "names"))  # weights only: a config path never runs code
    with reading(path, what):  # a config of other fields, weights that are not tensors
        model = YoloDetector(DetectorConfig(**ckpt["config"]))
        state = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["model"].items()}
        ckpt["names"] = [str(n) for n in ckpt["names"]]
    # tensors of another shape than the network the file's config builds: one line naming the first of them
    load_state(model, state, path, what, looks_like=lambda st: _looks_like(st, model.cfg, len(ckpt["names"])))
    return model, ckpt


def _looks_like(state: Mapping[str, Any], cfg: DetectorConfig, n_names: int) -> str:
    """What a detector state dict's tensors were made for (classes, width, mask prototypes) against its config."""
    def out(key: str) -> int | None:
        t = state.get(key)
        return int(t.shape[0]) if isinstance(t, torch.Tensor) and t.ndim >= 1 else None

    nc, c1, nm = out("head.cls.0.2.bias"), out("stem.0.conv.weight"), out("head.coef.0.2.bias")
    if nc is None or c1 is None:
        return ""
    width = cfg.width if cfg.width is not None else SCALES[cfg.scale][1] if cfg.scale in SCALES else None
    said = f"{cfg.num_classes} classes" + (f", width {width:g}" if width is not None else "") + f", {cfg.masks} masks"
    return (f"its tensors are a detector of {nc} classes, width ~{c1 / 64:g} ({c1} stem channels), {nm or 0} masks; "
            f"its config says {said}, and it names {n_names} classes")


def load_detector(path: str | Path, img_size: int = 640, conf: float = 0.25, device: torch.device | str = "cpu",
                  field: str = "slam.dynamic.weights") -> Any:
    """The detector a checkpoint holds, in either format: a network of the registry (``{arch, conf, state_dict,
    meta}``, ``vslam.nn.checkpoint.save_model``; a YOLOX -> ``YoloxDetector`` at its ``input_size``) or the
    from-scratch detector's ``{model, config, names}`` (-> ``Detector`` at the size it was trained at, else
    ``img_size``). Both return ``Detections`` from ``detect(image)``."""
    from vslam.nn.checkpoint import FORMAT_KEYS, read_checkpoint

    if not Path(path).is_file():
        raise ConfigError(f"{path}: detector weights not found ({field})")
    if all(k in read_checkpoint(path, "detector checkpoint") for k in FORMAT_KEYS):
        return _load_registry_detector(path, conf, device, field)
    model, ckpt = load_model(path, field)
    return Detector(model, ckpt["names"], img_size=int(ckpt.get("img_size", img_size)), conf=conf, device=device)


def _load_registry_detector(path: str | Path, conf: float, device: torch.device | str, field: str) -> Any:
    from vslam.dynamic.yolox_detector import YoloxDetector
    from vslam.nn.checkpoint import load_model as load_registry_model
    from vslam.nn.detectors.yolox import YOLOX
    from vslam.nn.registry import DETECTORS

    model, _ = load_registry_model(path, DETECTORS, field)
    if not isinstance(model, YOLOX):
        raise ConfigError(f"{path}: detector {type(model).__name__} has no inference wrapper ({field})")
    return YoloxDetector(model, img_size=int(model.conf["input_size"]), conf=conf, device=device)
