"""A YOLOX-style detector (Ge et al., "YOLOX: Exceeding YOLO Series in 2021", arXiv 2107.08430): CSPDarknet
backbone with a Focus stem and an SPP block, PAFPN neck, decoupled anchor-free head (per level: a 1x1 stem, then
two 3x3 branches for classes and for box + objectness). ``depthwise`` replaces the 3x3 convolutions by depthwise +
pointwise pairs (the nano and tiny models). Layer names follow Megvii's code, so the public YOLOX weights map onto
this network one layer to one layer (``vslam.nn.weights.yolox``).

Every convolution keeps its BatchNorm, also when it is loaded from a file whose BatchNorm was folded into the
convolutions (the public ONNX export): the network stays the one that is fine-tuned, and ``fuse_conv_bn`` folds
them again for inference.

Attention (seed 003's ablation: none / SE / CBAM / ESEA) sits on the three neck outputs, before the head, inside a
``GatedAttention`` whose residual gate starts at zero: with the public weights loaded, the network with attention
gives exactly the outputs of the network without it, and fine-tuning decides how much attention to let in.

Class rows: ``classes`` names the network's classes (their count sizes the class head); a converter from a COCO
checkpoint keeps the rows of those names, so a model of the six SLAM classes is the COCO model's output for them.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
from torch import nn

from vslam.nn.attention import GatedAttention, make_attention
from vslam.nn.base import BaseModel
from vslam.nn.detectors.coco import COCO80
from vslam.errors import ConfigError

BN_EPS, BN_MOMENTUM = 1e-3, 0.03  # Megvii's YOLOX BatchNorm settings (fine-tuning keeps them)
STRIDES = (8, 16, 32)


class BaseConv(nn.Module):
    """Conv (no bias) -> BatchNorm -> SiLU."""

    def __init__(self, c1: int, c2: int, k: int, s: int = 1, groups: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(c1, c2, k, s, (k - 1) // 2, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(c2, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class DWConv(nn.Module):
    """Depthwise k x k (stride ``s``) then pointwise 1x1, each a BaseConv."""

    def __init__(self, c1: int, c2: int, k: int, s: int = 1):
        super().__init__()
        self.dconv = BaseConv(c1, c1, k, s, groups=c1)
        self.pconv = BaseConv(c1, c2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pconv(self.dconv(x))


def _conv(depthwise: bool):
    return DWConv if depthwise else BaseConv


class Bottleneck(nn.Module):
    def __init__(self, c1: int, c2: int, shortcut: bool, depthwise: bool):
        super().__init__()
        self.conv1 = BaseConv(c1, c2, 1)
        self.conv2 = _conv(depthwise)(c2, c2, 3)
        self.use_add = shortcut and c1 == c2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv2(self.conv1(x))
        return y + x if self.use_add else y


class CSPLayer(nn.Module):
    """Cross-stage partial block: two 1x1 halves, ``n`` bottlenecks on one, concatenated, 1x1 out."""

    def __init__(self, c1: int, c2: int, n: int, shortcut: bool, depthwise: bool):
        super().__init__()
        h = c2 // 2
        # registered in the order they run (conv1, conv2, m, conv3): the public weights map by that order
        self.conv1, self.conv2 = BaseConv(c1, h, 1), BaseConv(c1, h, 1)
        self.m = nn.Sequential(*[Bottleneck(h, h, shortcut, depthwise) for _ in range(n)])
        self.conv3 = BaseConv(2 * h, c2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv3(torch.cat([self.m(self.conv1(x)), self.conv2(x)], 1))


class SPPBottleneck(nn.Module):
    """1x1 halving, max-pools of 5 / 9 / 13 concatenated with their input, 1x1 out."""

    def __init__(self, c1: int, c2: int, kernels: tuple[int, ...] = (5, 9, 13)):
        super().__init__()
        h = c1 // 2
        self.conv1 = BaseConv(c1, h, 1)
        self.m = nn.ModuleList(nn.MaxPool2d(k, 1, k // 2) for k in kernels)
        self.conv2 = BaseConv(h * (len(kernels) + 1), c2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv1(x)
        return self.conv2(torch.cat([x] + [m(x) for m in self.m], 1))


class Focus(nn.Module):
    """Space to depth (each 2x2 pixel block to 4 channels, in Megvii's order: top-left, bottom-left, top-right,
    bottom-right) then a 3x3 conv: stride 2 without losing a pixel."""

    def __init__(self, c1: int, c2: int):
        super().__init__()
        self.conv = BaseConv(4 * c1, c2, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(torch.cat([x[..., ::2, ::2], x[..., 1::2, ::2], x[..., ::2, 1::2], x[..., 1::2, 1::2]], 1))


class CSPDarknet(nn.Module):
    """-> features at strides 8, 16, 32 with 4w, 8w, 16w channels (w = 64 * width)."""

    def __init__(self, depth: float, width: float, depthwise: bool):
        super().__init__()
        conv = _conv(depthwise)
        c, n = int(width * 64), max(round(depth * 3), 1)
        self.stem = Focus(3, c)
        self.dark2 = nn.Sequential(conv(c, 2 * c, 3, 2), CSPLayer(2 * c, 2 * c, n, True, depthwise))
        self.dark3 = nn.Sequential(conv(2 * c, 4 * c, 3, 2), CSPLayer(4 * c, 4 * c, 3 * n, True, depthwise))
        self.dark4 = nn.Sequential(conv(4 * c, 8 * c, 3, 2), CSPLayer(8 * c, 8 * c, 3 * n, True, depthwise))
        self.dark5 = nn.Sequential(conv(8 * c, 16 * c, 3, 2), SPPBottleneck(16 * c, 16 * c),
                                   CSPLayer(16 * c, 16 * c, n, False, depthwise))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        c3 = self.dark3(self.dark2(self.stem(x)))
        c4 = self.dark4(c3)
        return c3, c4, self.dark5(c4)


class PAFPN(nn.Module):
    """Top-down then bottom-up path aggregation over the backbone's three levels (Megvii's layer names)."""

    def __init__(self, depth: float, width: float, depthwise: bool):
        super().__init__()
        conv = _conv(depthwise)
        c, n = int(width * 64), max(round(depth * 3), 1)
        self.backbone = CSPDarknet(depth, width, depthwise)
        self.upsample = nn.Upsample(scale_factor=2, mode="nearest")
        self.lateral_conv0 = BaseConv(16 * c, 8 * c, 1)
        self.C3_p4 = CSPLayer(16 * c, 8 * c, n, False, depthwise)
        self.reduce_conv1 = BaseConv(8 * c, 4 * c, 1)
        self.C3_p3 = CSPLayer(8 * c, 4 * c, n, False, depthwise)
        self.bu_conv2 = conv(4 * c, 4 * c, 3, 2)
        self.C3_n3 = CSPLayer(8 * c, 8 * c, n, False, depthwise)
        self.bu_conv1 = conv(8 * c, 8 * c, 3, 2)
        self.C3_n4 = CSPLayer(16 * c, 16 * c, n, False, depthwise)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x2, x1, x0 = self.backbone(x)
        fpn_out0 = self.lateral_conv0(x0)
        f_out0 = self.C3_p4(torch.cat([self.upsample(fpn_out0), x1], 1))
        fpn_out1 = self.reduce_conv1(f_out0)
        pan_out2 = self.C3_p3(torch.cat([self.upsample(fpn_out1), x2], 1))
        pan_out1 = self.C3_n3(torch.cat([self.bu_conv2(pan_out2), fpn_out1], 1))
        pan_out0 = self.C3_n4(torch.cat([self.bu_conv1(pan_out1), fpn_out0], 1))
        return pan_out2, pan_out1, pan_out0


class YOLOXHead(nn.Module):
    """Per level: 1x1 stem to 4w channels, two 3x3 class convs -> class logits, two 3x3 box convs -> 4 box
    values and 1 objectness logit."""

    def __init__(self, num_classes: int, width: float, depthwise: bool):
        super().__init__()
        conv, h = _conv(depthwise), int(256 * width)
        ins = [int(c * width) for c in (256, 512, 1024)]
        self.stems = nn.ModuleList(BaseConv(c, h, 1) for c in ins)
        self.cls_convs = nn.ModuleList(nn.Sequential(conv(h, h, 3), conv(h, h, 3)) for _ in ins)
        self.reg_convs = nn.ModuleList(nn.Sequential(conv(h, h, 3), conv(h, h, 3)) for _ in ins)
        self.cls_preds = nn.ModuleList(nn.Conv2d(h, num_classes, 1) for _ in ins)
        self.reg_preds = nn.ModuleList(nn.Conv2d(h, 4, 1) for _ in ins)
        self.obj_preds = nn.ModuleList(nn.Conv2d(h, 1, 1) for _ in ins)

    def forward(self, feats: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
        """-> per level (B, 5 + nc, H, W): box values (raw), objectness logit, class logits."""
        out = []
        for k, x in enumerate(feats):
            x = self.stems[k](x)
            reg = self.reg_convs[k](x)
            out.append(torch.cat([self.reg_preds[k](reg), self.obj_preds[k](reg), self.cls_preds[k](self.cls_convs[k](x))], 1))
        return out


def grid(shapes: list[tuple[int, int]], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor points of the levels of ``shapes`` ((h, w) each, strides ``STRIDES``), row-major per level:
    -> xy (A, 2) cell indices, stride (A, 1)."""
    xys, ss = [], []
    for (h, w), s in zip(shapes, STRIDES):
        yv, xv = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
        xys.append(torch.stack([xv, yv], -1).reshape(-1, 2))
        ss.append(torch.full((h * w, 1), float(s), device=device))
    return torch.cat(xys).float(), torch.cat(ss)


class YOLOX(BaseModel):
    """YOLOX-style detector.

    conf: ``depth`` / ``width`` (multipliers of the CSPDarknet-53 block counts and 64-channel base; nano 0.33 /
    0.25), ``depthwise``, ``classes`` (class names; their count sizes the class head), ``attention`` (none / se /
    cbam / esea at the neck outputs, zero-gated), ``input_size`` (the square input side the weights were trained
    at, the inference default; any multiple of 32 runs, also non-square).

    Input ``image``: (B, 3, H, W) float32, BGR, 0..255 (no mean / std: Megvii's convention since YOLOX 0.1.1), H
    and W multiples of 32. Outputs, A = H W (1/64 + 1/256 + 1/1024) anchors in level order (stride 8, 16, 32),
    row-major within a level:

    - ``pred`` (B, A, 5 + nc): the public export's layout: box values as regressed (x, y offsets in cells, log
      w, h), objectness and class probabilities (sigmoids);
    - ``logits`` (B, A, 5 + nc): the same before the sigmoids (what a training loss reads);
    - ``boxes`` (B, A, 4): x1, y1, x2, y2 input pixels (centre = (offset + cell) * stride, size = exp * stride);
    - ``scores`` (B, A, nc): objectness times class probability.
    """

    default_conf: dict[str, Any] = {
        "depth": 1.0, "width": 1.0, "depthwise": True, "classes": list(COCO80), "attention": "none",
        "input_size": 416,
    }
    required_inputs = ("image",)

    def _init(self, conf: dict[str, Any]) -> None:
        if conf["attention"] not in ("none", "se", "cbam", "esea"):
            raise ConfigError(f"YOLOX: attention must be none, se, cbam or esea, got {conf['attention']!r}")
        if not conf["classes"] or len(set(conf["classes"])) != len(conf["classes"]):
            raise ConfigError("YOLOX: classes must be a non-empty list of distinct names")
        if int(conf["input_size"]) <= 0 or int(conf["input_size"]) % 32:
            raise ConfigError(f"YOLOX: input_size must be a positive multiple of 32, got {conf['input_size']}")
        d, w, dw = float(conf["depth"]), float(conf["width"]), bool(conf["depthwise"])
        self.names = [str(n) for n in conf["classes"]]
        self.neck = PAFPN(d, w, dw)
        chans = [int(c * w) for c in (256, 512, 1024)]
        att = conf["attention"]
        self.attention = nn.ModuleList(
            nn.Identity() if att == "none" else GatedAttention(make_attention(att, c), c) for c in chans)
        self.head = YOLOXHead(len(self.names), w, dw)

    def _forward(self, data: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        x = data["image"]
        # backbone + neck: three levels; attention (the identity until its gates move) on each
        feats = tuple(a(f) for a, f in zip(self.attention, self.neck(x)))
        # head: per level (B, 5 + nc, h, w) -> anchors in row-major order, levels concatenated
        levels = self.head(feats)
        logits = torch.cat([o.flatten(2) for o in levels], 2).transpose(1, 2)
        pred = torch.cat([logits[..., :4], logits[..., 4:].sigmoid()], -1)
        # decoding: anchor-free, one box per cell centre offset
        xy, stride = grid([tuple(o.shape[2:]) for o in levels], x.device)
        c = (pred[..., :2] + xy) * stride
        half = pred[..., 2:4].exp() * stride / 2
        return {"pred": pred, "logits": logits, "boxes": torch.cat([c - half, c + half], -1),
                "scores": pred[..., 4:5] * pred[..., 5:]}


def conv_order(model: YOLOX) -> list[tuple[str, nn.Module]]:
    """(name, layer) of every convolution in the order the source network runs them (its ONNX export's node
    order): BaseConvs (a conv + its BN) and the head's bare prediction convs; the attention blocks are not in it."""
    out = [(f"neck.{n}", m) for n, m in model.neck.named_modules() if isinstance(m, BaseConv)]
    h = model.head
    for k in range(len(h.stems)):
        out.append((f"head.stems.{k}", h.stems[k]))
        for branch, pred in (("cls", ["cls_preds"]), ("reg", ["reg_preds", "obj_preds"])):
            convs = getattr(h, f"{branch}_convs")[k]
            out += [(f"head.{branch}_convs.{k}.{n}", m) for n, m in convs.named_modules() if isinstance(m, BaseConv)]
            out += [(f"head.{p}.{k}", getattr(h, p)[k]) for p in pred]
    return out


def fuse_conv_bn(model: nn.Module) -> nn.Module:
    """``model`` with every BaseConv's BatchNorm folded into its convolution (eval-mode arithmetic, in place):
    the inference form, one op fewer per layer. Training needs the unfused network."""
    for m in model.modules():
        if isinstance(m, BaseConv) and isinstance(m.bn, nn.BatchNorm2d):
            m.conv = torch.nn.utils.fusion.fuse_conv_bn_eval(m.conv.eval(), m.bn.eval())
            m.bn = nn.Identity()
    return model
