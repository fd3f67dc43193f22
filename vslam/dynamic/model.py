"""YOLOv8-like anchor-free one-stage detector in plain torch (no ultralytics), with a pluggable attention block.

Layout follows YOLOv8 (Jocher et al., Ultralytics 2023): a CSP backbone of C2f blocks with SPPF, a PAN neck
(top-down then bottom-up fusion) and a decoupled head per stride (8, 16, 32) with separate box and class
branches; boxes are distances to the four sides as a discrete distribution (DFL, Li et al., "Generalized Focal
Loss", NeurIPS 2020). The seed's change is an attention block: here one per neck output (P3, P4, P5), right
before the head, so the ablation none / SE / CBAM / ESEA changes nothing else.

Instance masks (``masks`` > 0) follow YOLACT (Bolya et al., ICCV 2019) as YOLOv8-seg does: a prototype branch
on the finest neck level gives ``masks`` maps at 1/4 of the input, and each anchor predicts as many mixing
coefficients; an instance's mask is sigmoid(coefficients . prototypes) cropped to its box. The masks cost one
small branch on top of the detector, so SLAM can mask a walker's pixels instead of its whole box.

forward(x: (B,3,H,W) float in [0,1], H and W multiples of 32) -> list of 3 maps (B, 4*reg_max + nc + masks,
H/s, W/s), and with a mask head a fourth entry: the prototypes (B, masks, H/4, W/4).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch
from torch import nn

from vslam.dynamic.attention import make_attention

SCALES = {"n": (0.33, 0.25, 1024), "s": (0.33, 0.50, 1024)}  # depth multiple, width multiple, max channels
STRIDES = (8, 16, 32)


@dataclass(frozen=True)
class DetectorConfig:
    scale: str = "n"
    attention: str = "none"  # none | se | cbam | esea
    num_classes: int = 1
    reg_max: int = 16
    width: float | None = None  # overrides the scale's width multiple (tiny test models)
    masks: int = 0  # prototype masks of the instance-mask head; 0 = boxes only


class Conv(nn.Module):
    """Conv2d + BatchNorm + SiLU."""

    def __init__(self, c1: int, c2: int, k: int = 1, s: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(c1, c2, k, s, k // 2, bias=False)
        self.bn = nn.BatchNorm2d(c2, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    def __init__(self, c: int, shortcut: bool = True):
        super().__init__()
        self.cv1, self.cv2, self.add = Conv(c, c, 3), Conv(c, c, 3), shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """CSP bottleneck with 2 convolutions (YOLOv8): split, n bottlenecks, concatenate every intermediate."""

    def __init__(self, c1: int, c2: int, n: int = 1, shortcut: bool = False):
        super().__init__()
        self.c = c2 // 2
        self.cv1 = Conv(c1, 2 * self.c, 1)
        self.cv2 = Conv((2 + n) * self.c, c2, 1)
        self.m = nn.ModuleList(Bottleneck(self.c, shortcut) for _ in range(n))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = list(self.cv1(x).chunk(2, 1))
        for m in self.m:
            y.append(m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class SPPF(nn.Module):
    """Spatial pyramid pooling, fast: three chained 5x5 max-pools (receptive fields 5, 9, 13)."""

    def __init__(self, c1: int, c2: int, k: int = 5):
        super().__init__()
        c_ = c1 // 2
        self.cv1, self.cv2 = Conv(c1, c_, 1), Conv(c_ * 4, c2, 1)
        self.m = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.m(y[-1]))
        return self.cv2(torch.cat(y, 1))


class DFL(nn.Module):
    """Expected value of the per-side distance distribution: (B, 4*R, A) -> (B, 4, A) in stride units."""

    def __init__(self, reg_max: int):
        super().__init__()
        self.register_buffer("proj", torch.arange(reg_max, dtype=torch.float32), persistent=False)
        self.reg_max = reg_max

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, a = x.shape
        return (x.view(b, 4, self.reg_max, a).softmax(2) * self.proj.view(1, 1, -1, 1)).sum(2)


class Head(nn.Module):
    """Decoupled head: per level a box branch (4*reg_max DFL logits), a class branch (nc logits) and, with a mask
    head, a coefficient branch (nm mixing weights of the prototypes)."""

    def __init__(self, nc: int, ch: tuple[int, ...], reg_max: int, nm: int = 0):
        super().__init__()
        self.nc, self.reg_max, self.nm = nc, reg_max, nm
        c2, c3 = max(16, ch[0] // 4, reg_max * 4), max(ch[0], min(nc, 100))
        self.box = nn.ModuleList(nn.Sequential(Conv(c, c2, 3), Conv(c2, c2, 3), nn.Conv2d(c2, 4 * reg_max, 1)) for c in ch)
        self.cls = nn.ModuleList(nn.Sequential(Conv(c, c3, 3), Conv(c3, c3, 3), nn.Conv2d(c3, nc, 1)) for c in ch)
        for b, c, s in zip(self.box, self.cls, STRIDES):  # YOLOv8 bias init: boxes ~1, rare classes at start
            b[-1].bias.data[:] = 1.0
            c[-1].bias.data[:] = math.log(5 / nc / (640 / s) ** 2)
        if nm:
            c4 = max(ch[0] // 4, nm)
            self.coef = nn.ModuleList(nn.Sequential(Conv(c, c4, 3), Conv(c4, c4, 3), nn.Conv2d(c4, nm, 1)) for c in ch)

    def forward(self, xs: list[torch.Tensor]) -> list[torch.Tensor]:
        if not self.nm:
            return [torch.cat([b(x), c(x)], 1) for x, b, c in zip(xs, self.box, self.cls)]
        return [torch.cat([b(x), c(x), m(x)], 1) for x, b, c, m in zip(xs, self.box, self.cls, self.coef)]


class Proto(nn.Module):
    """Prototype masks at 1/4 of the input from the stride-8 neck level (YOLOv8-seg's layout: conv, 2x transposed
    conv, conv, 1x1 to ``nm`` maps)."""

    def __init__(self, c1: int, c_: int, nm: int):
        super().__init__()
        self.cv1 = Conv(c1, c_, 3)
        self.up = nn.ConvTranspose2d(c_, c_, 2, 2, 0, bias=True)
        self.cv2 = Conv(c_, c_, 3)
        self.cv3 = Conv(c_, nm, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.cv3(self.cv2(self.up(self.cv1(x))))


class YoloDetector(nn.Module):
    def __init__(self, cfg: DetectorConfig = DetectorConfig()):
        super().__init__()
        if cfg.scale not in SCALES:
            raise ValueError(f"unknown detector scale {cfg.scale!r} (known: {', '.join(SCALES)})")
        self.cfg = cfg
        gd, gw, mc = SCALES[cfg.scale]
        gw = cfg.width if cfg.width is not None else gw

        def ch(c: int) -> int:
            return max(8, int(math.ceil(min(c, mc) * gw / 8) * 8))

        def n(k: int) -> int:
            return max(round(k * gd), 1)

        c1, c2, c3, c4, c5 = ch(64), ch(128), ch(256), ch(512), ch(1024)
        self.stem = nn.Sequential(Conv(3, c1, 3, 2), Conv(c1, c2, 3, 2), C2f(c2, c2, n(3), True))
        self.down3 = nn.Sequential(Conv(c2, c3, 3, 2), C2f(c3, c3, n(6), True))  # P3/8
        self.down4 = nn.Sequential(Conv(c3, c4, 3, 2), C2f(c4, c4, n(6), True))  # P4/16
        self.down5 = nn.Sequential(Conv(c4, c5, 3, 2), C2f(c5, c5, n(3), True), SPPF(c5, c5))  # P5/32
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.td4 = C2f(c5 + c4, c4, n(3))
        self.td3 = C2f(c4 + c3, c3, n(3))
        self.bu4_down, self.bu4 = Conv(c3, c3, 3, 2), C2f(c3 + c4, c4, n(3))
        self.bu5_down, self.bu5 = Conv(c4, c4, 3, 2), C2f(c4 + c5, c5, n(3))
        self.att = nn.ModuleList(make_attention(cfg.attention, c) for c in (c3, c4, c5))
        self.head = Head(cfg.num_classes, (c3, c4, c5), cfg.reg_max, cfg.masks)
        self.proto = Proto(c3, c3, cfg.masks) if cfg.masks else None
        self.dfl = DFL(cfg.reg_max)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        p3 = self.down3(self.stem(x))
        p4 = self.down4(p3)
        p5 = self.down5(p4)
        t4 = self.td4(torch.cat([self.up(p5), p4], 1))  # PAN top-down
        n3 = self.td3(torch.cat([self.up(t4), p3], 1))
        n4 = self.bu4(torch.cat([self.bu4_down(n3), t4], 1))  # bottom-up
        n5 = self.bu5(torch.cat([self.bu5_down(n4), p5], 1))
        xs = [a(f) for a, f in zip(self.att, (n3, n4, n5))]
        out = self.head(xs)
        return out if self.proto is None else [*out, self.proto(xs[0])]


def make_anchors(feats: list[torch.Tensor], offset: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor centres (A, 2) in grid units of their level and strides (A, 1), levels concatenated."""
    pts, strides = [], []
    for f, s in zip(feats, STRIDES):
        h, w = f.shape[2:]
        sy, sx = torch.meshgrid(torch.arange(h, device=f.device) + offset, torch.arange(w, device=f.device) + offset, indexing="ij")
        pts.append(torch.stack([sx, sy], -1).view(-1, 2).float())
        strides.append(torch.full((h * w, 1), float(s), device=f.device))
    return torch.cat(pts), torch.cat(strides)


def dist2bbox(dist: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """(…, 4) left, top, right, bottom distances + (…, 2) centres -> (…, 4) x1, y1, x2, y2."""
    lt, rb = dist.chunk(2, -1)
    return torch.cat([anchors - lt, anchors + rb], -1)


def _per_anchor(feats: list[torch.Tensor]) -> torch.Tensor:
    """The levels' maps (not the prototypes) -> (B, A, channels), levels concatenated."""
    b = feats[0].shape[0]
    return torch.cat([f.view(b, f.shape[1], -1) for f in feats[:len(STRIDES)]], 2).permute(0, 2, 1)


def split_outputs(model: YoloDetector, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw maps -> DFL logits (B, A, 4*reg_max) and class logits (B, A, nc)."""
    x = _per_anchor(feats)
    r4 = 4 * model.cfg.reg_max
    return x[..., :r4], x[..., r4:r4 + model.cfg.num_classes]


def mask_outputs(model: YoloDetector, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw maps of a model with a mask head -> coefficients (B, A, nm) and prototypes (B, nm, H/4, W/4)."""
    if not model.cfg.masks or len(feats) <= len(STRIDES):
        raise ValueError("this detector has no mask head (DetectorConfig.masks = 0)")
    return _per_anchor(feats)[..., 4 * model.cfg.reg_max + model.cfg.num_classes:], feats[len(STRIDES)]


def assemble_masks(coef: torch.Tensor, proto: torch.Tensor, boxes: torch.Tensor, stride: float = 4.0) -> torch.Tensor:
    """Mask logits of K instances: coef (K, nm), proto (nm, h, w), boxes (K, 4) x1,y1,x2,y2 input pixels ->
    (K, h, w) logits, set to -inf-like outside each box (YOLACT's crop: a prototype's response elsewhere in the
    image belongs to other objects)."""
    k, (nm, h, w) = coef.shape[0], proto.shape
    logits = (coef @ proto.reshape(nm, -1)).view(k, h, w)
    return logits.masked_fill(~box_crop(boxes / stride, h, w), -20.0)


def box_crop(boxes: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(K, 4) boxes in the grid's pixels -> (K, h, w) bool, True at cells whose centre lies inside the box."""
    xs = torch.arange(w, device=boxes.device, dtype=boxes.dtype) + 0.5
    ys = torch.arange(h, device=boxes.device, dtype=boxes.dtype) + 0.5
    x1, y1, x2, y2 = (boxes[:, i, None] for i in range(4))
    return ((ys[None] >= y1) & (ys[None] < y2))[:, :, None] & ((xs[None] >= x1) & (xs[None] < x2))[:, None, :]


def decode(model: YoloDetector, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Raw maps -> boxes (B, A, 4) x1,y1,x2,y2 input pixels and class probabilities (B, A, nc)."""
    reg, cls = split_outputs(model, feats)
    anchors, strides = make_anchors(feats)
    dist = model.dfl(reg.permute(0, 2, 1)).permute(0, 2, 1)
    return dist2bbox(dist, anchors) * strides, cls.sigmoid()


@torch.no_grad()
def fuse_for_inference(model: YoloDetector) -> YoloDetector:
    """An eval-mode copy for deployment: each Conv's BatchNorm folded into its convolution, weights in
    channels-last layout (the input of ``detector.to_tensor`` already is). Outputs equal up to float rounding
    (~1e-5), and less time on the CPU (docs/speed.md, 'Small exact speed-ups quoted in code comments')."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    m = copy.deepcopy(model).eval()
    for mod in m.modules():
        if isinstance(mod, Conv) and isinstance(mod.bn, nn.BatchNorm2d):
            mod.conv, mod.bn = fuse_conv_bn_eval(mod.conv, mod.bn), nn.Identity()
    return m.to(memory_format=torch.channels_last)


@torch.no_grad()
def recalibrate_bn(model: nn.Module, batches: list[torch.Tensor], only: list[nn.Module] | None = None) -> None:
    """Set BatchNorm running statistics to the exact average over ``batches`` (train-mode forward passes).

    Short runs (toy mode, tests) leave the running averages near their initial values with YOLO's momentum of
    0.03, so eval-mode outputs would not match what was trained. ``only``: recalibrate the BatchNorms inside
    these modules and leave the others' statistics as they are (a frozen detector under a new mask head)."""
    scope = only if only is not None else [model]
    bns = [m for s in scope for m in s.modules() if isinstance(m, nn.BatchNorm2d)]
    saved = [m.momentum for m in bns]
    was_training = model.training
    for m in bns:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    if only is None:
        model.train()
    else:
        model.eval()
        for s in scope:
            s.train()
    for x in batches:
        model(x)
    for m, mom in zip(bns, saved):
        m.momentum = mom
    model.train(was_training)


def mask_head_modules(model: YoloDetector) -> list[nn.Module]:
    """The modules a mask head adds (prototypes, coefficient branches): what trains over a frozen detector."""
    return [model.proto, model.head.coef] if model.cfg.masks else []
