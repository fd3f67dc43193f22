"""Attention blocks for the detector ablation (seed 003: plain vs SE vs CBAM vs ESEA), by name.

- SE: Hu, Shen, Sun, "Squeeze-and-Excitation Networks", CVPR 2018 — global average pool, FC C->C/r, ReLU,
  FC C/r->C, sigmoid, channel rescale.
- CBAM: Woo et al., "CBAM: Convolutional Block Attention Module", ECCV 2018 — channel attention from a shared
  MLP on average- and max-pooled features, then spatial attention from a 7x7 conv on the channel-wise mean and
  max maps, applied in sequence.
- ECA: Wang et al., "ECA-Net: Efficient Channel Attention", CVPR 2020 — shows that the dimensionality reduction
  of SE hurts and that a cheap cross-channel interaction without reduction is enough.
- eSE: Lee & Park, "CenterMask: Real-Time Anchor-Free Instance Segmentation", CVPR 2020 (VoVNetV2) — SE with one
  FC (a 1x1 conv on the pooled vector), no reduction, hard sigmoid.

ESEA (seed 003 names it, but does not define its layers) is designed here as "efficient squeeze-excitation +
spatial attention": the eSE/ECA-style channel branch (one 1x1 conv C->C on the global average pool, no
reduction, hard sigmoid) followed by CBAM's spatial branch (7x7 conv on [mean, max] over channels, sigmoid).
It keeps CBAM's "what" + "where" split while its channel branch has no bottleneck and no second pooled path:
C^2 + C + 98 weights against CBAM's 2 C^2/r + 98 and SE's 2 C^2/r, at one pooled vector per block.
Tensors: x (B, C, H, W) -> same shape.

``GatedAttention`` wraps a block as ``x + g * (block(x) - x)`` with a per-channel gate ``g`` that starts at zero:
a pretrained network gains the block without any change of its outputs (the block is exactly the identity until
fine-tuning moves ``g``; ReZero / LayerScale use the same zero-initialised residual scale).
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn


class SE(nn.Module):
    def __init__(self, c: int, reduction: int = 16):
        super().__init__()
        h = max(8, c // reduction)
        self.fc = nn.Sequential(nn.Conv2d(c, h, 1), nn.ReLU(inplace=True), nn.Conv2d(h, c, 1), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.fc(x.mean((2, 3), keepdim=True))


class SpatialAttention(nn.Module):
    """CBAM's spatial branch: sigmoid(conv7x7([mean_c(x), max_c(x)])) * x."""

    def __init__(self, kernel: int = 7):
        super().__init__()
        self.conv = nn.Conv2d(2, 1, kernel, padding=kernel // 2, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = torch.cat([x.mean(1, keepdim=True), x.amax(1, keepdim=True)], 1)
        return x * torch.sigmoid(self.conv(s))


class CBAM(nn.Module):
    def __init__(self, c: int, reduction: int = 16):
        super().__init__()
        h = max(8, c // reduction)
        self.mlp = nn.Sequential(nn.Conv2d(c, h, 1, bias=False), nn.ReLU(inplace=True), nn.Conv2d(h, c, 1, bias=False))
        self.spatial = SpatialAttention()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.mlp(x.mean((2, 3), keepdim=True)) + self.mlp(x.amax((2, 3), keepdim=True))
        return self.spatial(x * torch.sigmoid(a))


class ESEA(nn.Module):
    """Efficient SE channel branch (1x1 conv on the pooled vector, no reduction, hard sigmoid) + spatial branch."""

    def __init__(self, c: int):
        super().__init__()
        self.fc = nn.Conv2d(c, c, 1)
        self.gate = nn.Hardsigmoid()
        self.spatial = SpatialAttention()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.spatial(x * self.gate(self.fc(x.mean((2, 3), keepdim=True))))


ATTENTION: dict[str, Callable[[int], nn.Module]] = {
    "none": lambda c: nn.Identity(),
    "se": SE,
    "cbam": CBAM,
    "esea": ESEA,
}


class GatedAttention(nn.Module):
    """``x + gate * (block(x) - x)``, ``gate`` (C,) initialised to zero: exactly ``x`` at the start (0 times a
    finite number is 0 in floating point), and the gradient reaches ``gate`` from the first step (that of the
    block follows once ``gate`` is non-zero)."""

    def __init__(self, block: nn.Module, c: int):
        super().__init__()
        self.block = block
        self.gate = nn.Parameter(torch.zeros(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.gate.view(1, -1, 1, 1) * (self.block(x) - x)


def make_attention(name: str, c: int) -> nn.Module:
    if name not in ATTENTION:
        raise ValueError(f"unknown attention {name!r} (known: {', '.join(ATTENTION)})")
    return ATTENTION[name](c)
