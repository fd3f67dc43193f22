"""Instance masks for the YOLOX-style detector: a box-prompted mask head over the unchanged YOLOX network.

The detector's boxes prompt the head, as a Mask R-CNN mask branch (He et al., "Mask R-CNN", ICCV 2017): per box,
RoIAlign of the stride-8 neck output (the finest level the head reads) gives coarse features of the object, and
RoIAlign of the network's own input image at four times that resolution gives the outline's detail (a small
refinement decoder, as in the upsampling path of a U-Net). The head predicts one class-agnostic mask logit map over
the box grown by ``margin`` (a detector's box may cut off a hand or a foot). It was chosen over YOLACT-style
prototypes + per-box coefficients (Bolya et al., ICCV 2019) because its masks are made in the box's own frame:
a prototype cell at stride 4-8 is ~10 px of a 640x480 frame, and the from-scratch detector's prototype masks
leak at exactly those outlines (docs/dynamic.md, "Instance masks").

``YOLOXMasks`` is ``YOLOX`` with the head added: the box network runs exactly as in ``YOLOX`` (same modules, same
state-dict names, same outputs bit for bit); the neck outputs the box head reads are taken with a forward
pre-hook on the head, so a change to the class head or the decoding in ``yolox.py`` reaches this model as it is.
A YOLOX checkpoint loads into it with the mask head's parameters missing (``mask_head.*``).
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import nn

from vslam.errors import ConfigError
from vslam.nn.detectors.yolox import YOLOX

MASK_DEFAULTS: dict[str, Any] = {
    "roi": 14,  # RoIAlign side on the stride-8 neck output
    "side": 56,  # side of the predicted mask logit map (the image branch's RoIAlign side)
    "channels": 32,  # width of the feature branch
    "image_channels": 16,  # width of the image branch
    "refine_convs": 1,  # 3x3 convolutions per upsampled level (side / 2, side)
    "margin": 0.1,  # the head's region: the box grown by this fraction of its width / height on every side
    "threshold": 0.5,  # mask probability cut at inference (the trainer picks it on Penn-Fudan train)
}


def _conv(c1: int, c2: int, s: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c1, c2, 3, s, 1), nn.ReLU(inplace=True))


def expand_boxes(boxes: torch.Tensor, margin: float) -> torch.Tensor:
    """(K, 4) x1, y1, x2, y2 -> the same boxes grown by ``margin`` of their width / height on every side."""
    d = (boxes[:, 2:] - boxes[:, :2]) * margin
    return torch.cat([boxes[:, :2] - d, boxes[:, 2:] + d], 1)


class BoxMaskHead(nn.Module):
    """feats P3 (B, C3, H/8, W/8), image (B, 3, H, W) BGR 0..255, rois (K, 5) (batch index, x1, y1, x2, y2 input
    pixels, the grown boxes) -> mask logits (K, side, side) over each roi."""

    def __init__(self, c3: int, roi: int, side: int, channels: int, image_channels: int, refine_convs: int = 1):
        super().__init__()
        if side != 4 * roi:
            raise ConfigError(f"YOLOX mask head: side must be 4 x roi (two 2x upsamplings), got side {side}, roi {roi}")
        c, ci = channels, image_channels
        self.roi, self.side = roi, side
        self.feat = nn.Sequential(_conv(c3, c), _conv(c, c))  # at roi
        self.img1 = _conv(3, ci)  # at side
        self.img2 = _conv(ci, ci, 2)  # at side / 2
        self.up1 = _conv(c + ci, c // 2)  # at side / 2
        self.up2 = _conv(c // 2 + ci, ci)  # at side
        if refine_convs < 1:
            raise ConfigError(f"YOLOX mask head: refine_convs must be >= 1, got {refine_convs}")
        # further convolutions per level (none at 1: the layers above are the whole head)
        self.more1 = nn.Sequential(*[_conv(c // 2, c // 2) for _ in range(refine_convs - 1)])
        self.more2 = nn.Sequential(*[_conv(ci, ci) for _ in range(refine_convs - 1)])
        self.out = nn.Conv2d(ci, 1, 1)

    def forward(self, p3: torch.Tensor, image: torch.Tensor, rois: torch.Tensor) -> torch.Tensor:
        from torchvision.ops import roi_align

        stride = image.shape[-1] / p3.shape[-1]
        f = roi_align(p3, rois, self.roi, 1.0 / stride, sampling_ratio=2, aligned=True)
        g = roi_align(image, rois, self.side, 1.0, sampling_ratio=1, aligned=True) / 127.5 - 1.0
        g1 = self.img1(g)
        g2 = self.img2(g1)
        f = self.feat(f)
        f = self.more1(self.up1(torch.cat([F.interpolate(f, scale_factor=2.0, mode="bilinear", align_corners=False), g2], 1)))
        f = self.more2(self.up2(torch.cat([F.interpolate(f, scale_factor=2.0, mode="bilinear", align_corners=False), g1], 1)))
        return self.out(f)[:, 0]


def _keep_head_input(module: nn.Module, args: tuple[Any, ...]) -> None:
    module.tapped_feats = args[0]


class YOLOXMasks(YOLOX):
    """``YOLOX`` with a box-prompted mask head (module docstring).

    conf: YOLOX's, plus ``mask`` (``MASK_DEFAULTS``: ``roi``, ``side``, ``channels``, ``image_channels``,
    ``refine_convs``, ``margin``, ``threshold``). Inputs: YOLOX's ``image`` and optionally ``mask_boxes``: a list of B (K_b, 4) tensors of x1, y1,
    x2, y2 input pixels (the detector's kept boxes at inference, the true boxes in training). Outputs: YOLOX's
    (unchanged), plus ``feats`` (the three neck outputs the box head read) and, with ``mask_boxes``,
    ``mask_logits`` (sum K_b, side, side) over each box grown by ``margin``, boxes in batch order, and
    ``mask_rois`` (sum K_b, 5) those grown boxes (batch index, x1, y1, x2, y2)."""

    default_conf: dict[str, Any] = {**YOLOX.default_conf, "mask": dict(MASK_DEFAULTS)}

    def _init(self, conf: dict[str, Any]) -> None:
        super()._init(conf)
        m = conf["mask"]
        if not 0.0 <= float(m["margin"]) <= 1.0:
            raise ConfigError(f"YOLOX mask head: margin must be in [0, 1], got {m['margin']}")
        if not 0.0 < float(m["threshold"]) < 1.0:
            raise ConfigError(f"YOLOX mask head: threshold must be in (0, 1), got {m['threshold']}")
        c3 = int(256 * float(conf["width"]))
        self.mask_head = BoxMaskHead(c3, int(m["roi"]), int(m["side"]), int(m["channels"]), int(m["image_channels"]),
                                     int(m["refine_convs"]))
        self.head.register_forward_pre_hook(_keep_head_input)

    def _forward(self, data: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        out = super()._forward(data)
        feats = self.head.__dict__.pop("tapped_feats")
        out["feats"] = feats
        if data.get("mask_boxes") is not None:
            rois = self.rois(data["mask_boxes"])
            out["mask_rois"] = rois
            out["mask_logits"] = self.mask_logits(feats, data["image"], rois)
        return out

    def rois(self, boxes: list[torch.Tensor]) -> torch.Tensor:
        """B lists of (K_b, 4) boxes -> (sum K_b, 5) grown rois with their batch index."""
        parts = [torch.cat([torch.full((len(b), 1), float(i), dtype=b.dtype, device=b.device),
                            expand_boxes(b, float(self.conf["mask"]["margin"]))], 1) for i, b in enumerate(boxes)]
        return torch.cat(parts) if parts else torch.zeros((0, 5))

    def mask_logits(self, feats: tuple[torch.Tensor, ...], image: torch.Tensor, rois: torch.Tensor) -> torch.Tensor:
        if not len(rois):
            s = int(self.conf["mask"]["side"])
            return image.new_zeros((0, s, s))
        return self.mask_head(feats[0], image, rois.to(image.dtype))
