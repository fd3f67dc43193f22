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
    """``detect(image)``: BGR or grey uint8 image -> Detections in that image's pixels (boxes clipped to it;
    instance masks where the network has a mask head (``YOLOXMasks``), else none). Runs a BN-fused copy of
    ``model`` on ``device``; the model passed in is left as it was. ``conf``: score (objectness x class
    probability) threshold; ``iou``: NMS IoU (Megvii's 0.45)."""

    def __init__(self, model: torch.nn.Module, img_size: int | tuple[int, int] = 416, wide: bool = False,
                 conf: float = 0.25, iou: float = 0.45, device: torch.device | str = "cpu"):
        import copy

        from vslam.nn.detectors.yolox import fuse_conv_bn

        self.device = torch.device(device)
        self.model = fuse_conv_bn(copy.deepcopy(model).eval()).to(self.device)
        self.names = list(model.names)
        self.img_size, self.wide, self.conf, self.iou = img_size, wide, conf, iou
        self.has_masks = hasattr(self.model, "mask_logits")

    def input_size(self, shape: tuple[int, int]) -> tuple[int, int]:
        w, h = input_shape(shape, self.img_size, self.wide)
        if w <= 0 or h <= 0 or w % 32 or h % 32:
            raise ConfigError(f"detector input {w}x{h}: sides must be positive multiples of 32")
        return w, h

    def _input(self, image: np.ndarray) -> tuple[torch.Tensor, float]:
        bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        im, r = letterbox_top_left(bgr, self.input_size(bgr.shape[:2]))
        return torch.from_numpy(im).to(self.device).permute(2, 0, 1)[None].float(), r

    @torch.inference_mode()
    def detect(self, image: np.ndarray) -> Detections:
        x, r = self._input(image)
        out = self.model({"image": x})
        bt, s, c = postprocess(out["boxes"], out["scores"], self.conf, self.iou)[0]
        b = bt.cpu().numpy().astype(np.float64) / r
        H, W = image.shape[:2]
        b[:, [0, 2]] = b[:, [0, 2]].clip(0, W)
        b[:, [1, 3]] = b[:, [1, 3]].clip(0, H)
        ids = c.cpu().numpy().astype(np.int64)
        masks, mask_px = None, 0.0
        if self.has_masks:
            masks, mask_px = self._masks(out["feats"], x, bt, r, (H, W))
        return Detections(b, s.cpu().numpy().astype(np.float64), ids,
                          np.array([self.names[i] for i in ids], dtype=object), masks, mask_px)

    def masks_for(self, image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """(K, H, W) bool masks of the mask head prompted with ``boxes`` (K, 4) image pixels instead of the
        detector's own (the teacher's protocol: true boxes in, masks out)."""
        logits, regions = self.prompted_logits(image, boxes)
        return paste_masks(logits, regions, image.shape[:2], self.mask_cut())[0]

    @torch.inference_mode()
    def prompted_logits(self, image: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The mask head's logit maps (K, S, S) for ``boxes`` (K, 4) image pixels, and their regions (K, 4) image
        pixels (the grown boxes)."""
        if not self.has_masks:
            raise ConfigError("this detector has no mask head (a boxes-only checkpoint)")
        x, r = self._input(image)
        out = self.model({"image": x})
        bt = torch.as_tensor(np.asarray(boxes, np.float64).reshape(-1, 4) * r, dtype=torch.float32, device=self.device)
        rois = self.model.rois([bt])
        logits = self.model.mask_logits(out["feats"], x, rois).float().cpu().numpy()
        return logits, rois[:, 1:].cpu().numpy().astype(np.float64) / r

    def mask_cut(self) -> float:
        """The logit the masks are cut at: the head's probability ``threshold``."""
        t = float(self.model.conf["mask"]["threshold"])
        return float(np.log(t / (1 - t)))

    def _masks(self, feats: tuple[torch.Tensor, ...], x: torch.Tensor, boxes: torch.Tensor, r: float,
               shape: tuple[int, int]) -> tuple[np.ndarray, float]:
        """Mask logits of ``boxes`` (K, 4 network-input pixels) pasted into the image -> (K, H, W) bool and the
        mean image pixels one mask cell spans (``Detections.mask_px``)."""
        rois = self.model.rois([boxes])
        logits = self.model.mask_logits(feats, x, rois).float().cpu().numpy()
        return paste_masks(logits, rois[:, 1:].cpu().numpy().astype(np.float64) / r, shape, self.mask_cut())


def paste_masks(logits: np.ndarray, regions: np.ndarray, shape: tuple[int, int],
                cut: float = 0.0) -> tuple[np.ndarray, float]:
    """Mask logit maps (K, S, S), each over its region (K, 4) x1, y1, x2, y2 image pixels, into the image: (K, H, W)
    bool, True where the bilinearly resized logit is above ``cut`` (0: probability 0.5); nothing outside the
    region. Also the mean region side / S (image pixels per mask cell)."""
    H, W = shape
    out = np.zeros((len(logits), H, W), bool)
    if not len(logits):
        return out, 0.0
    S = logits.shape[-1]
    for k, (lg, (x1, y1, x2, y2)) in enumerate(zip(logits, regions)):
        # the region's pixel-edge coordinates -> the map's: map u (pixel-centre convention) = (x + 0.5 - x1) sx - 0.5
        sx, sy = S / max(x2 - x1, 1e-6), S / max(y2 - y1, 1e-6)
        c0, r0, c1, r1 = max(int(np.floor(x1)), 0), max(int(np.floor(y1)), 0), min(int(np.ceil(x2)), W), min(int(np.ceil(y2)), H)
        if c1 <= c0 or r1 <= r0:
            continue
        A = np.array([[sx, 0.0, (c0 + 0.5 - x1) * sx - 0.5], [0.0, sy, (r0 + 0.5 - y1) * sy - 0.5]])
        # the region's outermost half cell lies beyond the map's outer cell centres: the edge cells hold there
        win = cv2.warpAffine(lg.astype(np.float32), A, (c1 - c0, r1 - r0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        out[k, r0:r1, c0:c1] = win > cut
    side = np.maximum(regions[:, 2] - regions[:, 0], regions[:, 3] - regions[:, 1])
    return out, float(np.mean(side) / S)
