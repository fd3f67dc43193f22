"""Inference wrapper around the YOLOX-style network of the registry: image in, ``Detections`` out (numpy at the
boundary), the same as the from-scratch detector's ``Detector`` so the dynamic filter, ``vslam eval-detector`` and
``vslam detect`` take either.

Preprocessing is the one the public weights were trained with (Megvii's ``ValTransform``): BGR, 0..255, no mean /
std, resized by one scale to fit the input and placed at the top-left of a grey (114) canvas. The input is
``img_size`` square by default (the source's 416x416); ``wide`` keeps the frame's aspect instead (the longer side
``img_size``, the shorter rounded up to a multiple of 32: a 1241x376 KITTI frame at 1248 runs at 1248x384, where a
square input would shrink its people to a third of the height). Decoding and class-aware NMS use
``vslam.nn.ops`` through ``detections.postprocess``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from vslam.dynamic.detections import Detections, postprocess
from vslam.errors import ConfigError

PAD_VALUE = 114


def input_shape(shape: tuple[int, int], img_size: int | tuple[int, int], wide: bool) -> tuple[int, int]:
    """(w, h) of the network input for an image of ``shape`` (h, w): ``img_size`` as (w, h) when a pair, else a
    square of ``img_size``, or with ``wide`` the image's aspect at longer side ``img_size`` (multiples of 32)."""
    if not isinstance(img_size, int):
        w, h = (int(v) for v in img_size)
        return w, h
    if not wide:
        return img_size, img_size
    H, W = shape[:2]
    r = img_size / max(H, W)
    return (math.ceil(W * r / 32) * 32, math.ceil(H * r / 32) * 32)


def letterbox_top_left(image: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, float]:
    """``image`` (H, W, 3) resized by r = min(w / W, h / H) (sizes truncated, as Megvii's ``preproc``) onto the
    top-left of a (h, w) canvas of grey 114 -> (canvas, r); input pixel = image pixel * r."""
    w, h = size
    H, W = image.shape[:2]
    r = min(w / W, h / H)
    nw, nh = int(W * r), int(H * r)
    out = np.full((h, w, 3), PAD_VALUE, np.uint8)
    out[:nh, :nw] = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR) if (nw, nh) != (W, H) else image
    return out, r


class YoloxDetector:
    """``detect(image)``: BGR or grey uint8 image -> Detections in that image's pixels (boxes clipped to it; no
    masks: the network has no mask head). Runs a BN-fused copy of ``model`` on ``device``; the model passed in is
    left as it was. ``conf``: score (objectness x class probability) threshold; ``iou``: NMS IoU (Megvii's 0.45)."""

    def __init__(self, model: torch.nn.Module, img_size: int | tuple[int, int] = 416, wide: bool = False,
                 conf: float = 0.25, iou: float = 0.45, device: torch.device | str = "cpu"):
        import copy

        from vslam.nn.detectors.yolox import fuse_conv_bn

        self.device = torch.device(device)
        self.model = fuse_conv_bn(copy.deepcopy(model).eval()).to(self.device)
        self.names = list(model.names)
        self.img_size, self.wide, self.conf, self.iou = img_size, wide, conf, iou

    def input_size(self, shape: tuple[int, int]) -> tuple[int, int]:
        w, h = input_shape(shape, self.img_size, self.wide)
        if w <= 0 or h <= 0 or w % 32 or h % 32:
            raise ConfigError(f"detector input {w}x{h}: sides must be positive multiples of 32")
        return w, h

    @torch.inference_mode()
    def detect(self, image: np.ndarray) -> Detections:
        bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        im, r = letterbox_top_left(bgr, self.input_size(bgr.shape[:2]))
        x = torch.from_numpy(im).to(self.device).permute(2, 0, 1)[None].float()
        out = self.model({"image": x})
        bt, s, c = postprocess(out["boxes"], out["scores"], self.conf, self.iou)[0]
        b = bt.cpu().numpy().astype(np.float64) / r
        H, W = image.shape[:2]
        b[:, [0, 2]] = b[:, [0, 2]].clip(0, W)
        b[:, [1, 3]] = b[:, [1, 3]].clip(0, H)
        ids = c.cpu().numpy().astype(np.int64)
        return Detections(b, s.cpu().numpy().astype(np.float64), ids,
                          np.array([self.names[i] for i in ids], dtype=object), None, 0.0)
