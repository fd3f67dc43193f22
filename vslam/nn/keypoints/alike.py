"""ALIKE (Zhao et al., "ALIKE: Accurate and Lightweight Keypoint Detection and Descriptor Extraction", IEEE TMM
2022): a four-level encoder, a 1x1 projection of every level to dim/4 channels, the levels upsampled to full
resolution and concatenated, and one 1x1 head giving dim descriptor channels plus one score channel. Our own
module; ``vslam.nn.weights.alike`` converts the public BSD-3-Clause checkpoints (t / s / n) onto it.

Two ways to the descriptors, the same numbers:

- ``dense``: the published way -- the head over the full-resolution concatenation, a (dim, H, W) map, normalised
  per pixel, bilinearly sampled at the keypoints. At KITTI size that map is two thirds of the network's cost.
- sparse (default): the score channel is linear in the concatenation and bilinear upsampling is linear, so the
  score map is the sum of each level's own 1-channel projection upsampled (one channel at full resolution instead
  of dim); descriptors are computed at the four pixels around each keypoint only (the level features there, then
  the head), normalised and interpolated exactly as the dense map would be. Same keypoints to float rounding.

Detection follows the published inference: sigmoid score map, NMS over a (2r+1)^2 window with two suppression
rounds, a border cleared, top-k (or a threshold), soft-argmax refinement in the (2r+1)^2 window at temperature
0.1, the score sampled bilinearly at the refined point.
"""

from __future__ import annotations

from typing import Any, Mapping

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from vslam.nn.base import BaseModel

# variant -> channels of the four encoder levels and the descriptor size (the published configurations)
VARIANTS: dict[str, tuple[int, int, int, int, int]] = {
    "t": (8, 16, 32, 64, 64),
    "s": (8, 16, 48, 96, 96),
    "n": (16, 32, 64, 128, 128),
}
STRIDES = (1, 2, 8, 32)  # of the four levels: pooling by 2, 4, 4 between them
PAD = 32  # the input is padded to a multiple of the coarsest stride


def _conv_bn(i: int, o: int) -> list[nn.Module]:
    return [nn.Conv2d(i, o, 3, padding=1, bias=False), nn.BatchNorm2d(o)]


class Residual(nn.Module):
    """Two 3x3 conv + BN with a ReLU between, plus a 1x1 projection of the input (channels change)."""

    def __init__(self, i: int, o: int):
        super().__init__()
        self.body = nn.Sequential(*_conv_bn(i, o), nn.ReLU(inplace=True), *_conv_bn(o, o))
        self.skip = nn.Conv2d(i, o, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.body(x) + self.skip(x), inplace=True)


def nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """(B,1,H,W) -> the same with every value zeroed that is not a local maximum in a (2r+1)^2 window; two further
    rounds let a maximum that was only suppressed by a suppressed neighbour come back (SuperPoint's NMS, as the
    published ALIKE code runs it). On the CPU with OpenCV's dilation (the same maxima, much faster than torch's
    max pooling, which cost more than the network at half resolution; docs/speed.md, 'Small exact speed-ups
    quoted in code comments')."""
    if scores.device.type == "cpu" and scores.dtype == torch.float32:
        return torch.from_numpy(np.stack([_nms_cv(s, radius) for s in scores[:, 0].numpy()]))[:, None]

    def window_max(x: torch.Tensor) -> torch.Tensor:  # separable: the same maxima as the square pool, fewer reads
        x = F.max_pool2d(x, (1, 2 * radius + 1), stride=1, padding=(0, radius))
        return F.max_pool2d(x, (2 * radius + 1, 1), stride=1, padding=(radius, 0))

    zeros = torch.zeros_like(scores)
    keep = scores == window_max(scores)
    for _ in range(2):
        near = window_max(keep.float()) > 0
        rest = torch.where(near, zeros, scores)
        keep = keep | ((rest == window_max(rest)) & ~near)
    return torch.where(keep, scores, zeros)


def _nms_cv(s: np.ndarray, radius: int) -> np.ndarray:
    """``nms`` of one (H,W) float32 map with cv2.dilate (a max filter; outside the image counts as -inf, as the
    padding of max pooling does)."""
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)

    def window_max(x: np.ndarray) -> np.ndarray:
        return cv2.dilate(x, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)

    keep = s == window_max(s)
    for _ in range(2):
        near = window_max(keep.astype(np.float32)) > 0
        rest = np.where(near, 0.0, s).astype(np.float32)
        keep |= (rest == window_max(rest)) & ~near
    return np.where(keep, s, 0.0).astype(np.float32)


class ALIKE(BaseModel):
    """Input ``image``: (B,3,H,W) float32 RGB in [0,1] (grey replicated), any H, W (padded to 32 inside).

    Output: ``scores_map`` (B,1,H,W) in (0,1); per image lists ``keypoints`` (N,2) x y pixels, ``scores`` (N,),
    ``descriptors`` (N,dim) unit length; keypoints by descending score. Conf: ``variant`` t/s/n; ``top_k`` > 0
    keeps the best k after NMS, else those above ``scores_th`` (at most ``n_limit``); ``dense``: descriptors from
    the full dense map (the published way) instead of at the keypoints only.
    """

    default_conf = {"variant": "t", "nms_radius": 2, "border": 3, "top_k": 500, "scores_th": 0.2, "n_limit": 5000,
                    "temperature": 0.1, "sub_pixel": True, "dense": False}
    required_inputs = ("image",)

    def _init(self, conf: dict[str, Any]) -> None:
        from vslam.errors import ConfigError

        if conf["variant"] not in VARIANTS:
            raise ConfigError(f"ALIKE variant: unknown {conf['variant']!r} (known: {', '.join(VARIANTS)})")
        c1, c2, c3, c4, dim = VARIANTS[conf["variant"]]
        self.dim = dim
        self.stem = nn.Sequential(*_conv_bn(3, c1), nn.ReLU(inplace=True), *_conv_bn(c1, c1), nn.ReLU(inplace=True))
        self.enc2, self.enc3, self.enc4 = Residual(c1, c2), Residual(c2, c3), Residual(c3, c4)
        q = dim // 4
        self.proj = nn.ModuleList(nn.Conv2d(c, q, 1, bias=False) for c in (c1, c2, c3, c4))
        self.head = nn.Conv2d(dim, dim + 1, 1, bias=False)  # dim descriptor channels, then the score logit

    def fused(self) -> ALIKE:
        """This network with every BatchNorm folded into the convolution before it (inference only: the state
        dict then has conv biases instead of BN tensors; outputs equal to float rounding)."""
        import copy

        net = copy.deepcopy(self).eval()
        for seq in (net.stem, net.enc2.body, net.enc3.body, net.enc4.body):
            for i, m in enumerate(seq):
                if isinstance(m, nn.BatchNorm2d):
                    conv = seq[i - 1]
                    g = m.weight / torch.sqrt(m.running_var + m.eps)
                    fused = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, padding=conv.padding)
                    fused.weight.data = conv.weight.data * g[:, None, None, None]
                    fused.bias.data = m.bias.data - m.running_mean * g
                    seq[i - 1], seq[i] = fused, nn.Identity()
        return net

    # ---------------------------------------------------------------- encoder
    def levels(self, image: torch.Tensor) -> list[torch.Tensor]:
        """(B,3,H,W) -> the four projected levels (B,dim/4,Hp/s,Wp/s), s = 1, 2, 8, 32; Hp, Wp: H, W padded with
        zeros at the bottom / right to a multiple of 32."""
        h, w = image.shape[-2:]
        image = F.pad(image, (0, -w % PAD, 0, -h % PAD))
        x1 = self.stem(image)
        x2 = self.enc2(F.max_pool2d(x1, 2))
        x3 = self.enc3(F.max_pool2d(x2, 4))
        x4 = self.enc4(F.max_pool2d(x3, 4))
        return [F.relu(p(x), inplace=True) for p, x in zip(self.proj, (x1, x2, x3, x4))]

    @staticmethod
    def _up(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        return F.interpolate(x, size=size, mode="bilinear", align_corners=True)

    def score_map(self, levels: list[torch.Tensor], hw: tuple[int, int]) -> torch.Tensor:
        """(B,1,H,W) sigmoid scores from each level's share of the head's score row, upsampled and summed (the
        head is linear and so is the upsampling: this equals the score channel of the dense head)."""
        q = self.dim // 4
        w = self.head.weight[-1:]  # (1, dim, 1, 1)
        full = levels[0].shape[-2:]
        s = F.conv2d(levels[0], w[:, :q])
        for k in (1, 2, 3):
            s = s + self._up(F.conv2d(levels[k], w[:, k * q:(k + 1) * q]), full)
        return torch.sigmoid(s[..., :hw[0], :hw[1]])

    def dense_maps(self, levels: list[torch.Tensor], hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The published head: ((B,dim,H,W) unit descriptors, (B,1,H,W) scores) from the full concatenation."""
        full = levels[0].shape[-2:]
        x = self.head(torch.cat([levels[0]] + [self._up(f, full) for f in levels[1:]], dim=1))
        x = x[..., :hw[0], :hw[1]]
        return F.normalize(x[:, :-1], dim=1), torch.sigmoid(x[:, -1:])

    # ---------------------------------------------------------------- detection
    def candidates(self, scores: torch.Tensor, top_k: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(H,W) score map of one image -> (flat indices (M,), their scores (M,)) of the NMS maxima off the border:
        the best ``top_k`` (conf's when None), or with top_k <= 0 those above ``scores_th`` (at most ``n_limit``,
        the best first; the mean score as threshold when none passes, as published)."""
        c = self.conf
        r, b = c["nms_radius"], c["border"]
        h, w = scores.shape
        s = nms(scores[None, None], r)[0, 0]
        # the published border: the (2r+1)^2 refinement window stays inside the image
        s[:b], s[:, :b], s[h - b + 1:], s[:, w - b + 1:] = 0, 0, 0, 0
        flat = s.reshape(-1)
        k = c["top_k"] if top_k is None else top_k
        if k > 0:
            v, i = torch.topk(flat, min(k, flat.numel()))
            return i, v
        th = c["scores_th"] if c["scores_th"] > 0 else float(scores.mean())
        i = torch.nonzero(flat > th)[:, 0]
        if len(i) == 0:
            i = torch.nonzero(flat > float(scores.mean()))[:, 0]
        v = flat[i]
        if len(i) > c["n_limit"]:
            v, o = torch.topk(v, c["n_limit"])
            i = i[o]
        return i, v

    def refine(self, scores: torch.Tensor, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Soft-argmax of the (2r+1)^2 scores around each candidate at ``temperature`` -> ((M,2) float x y pixels,
        (M,) the score map bilinearly sampled there). Without ``sub_pixel`` the integer maxima and their scores."""
        h, w = scores.shape
        y, x = idx // w, idx % w
        xy = torch.stack([x, y], 1).to(scores.dtype)
        if not self.conf["sub_pixel"]:
            return xy, scores.reshape(-1)[idx]
        r = self.conf["nms_radius"]
        d = torch.arange(-r, r + 1, device=scores.device)
        dy, dx = torch.meshgrid(d, d, indexing="ij")
        dx, dy = dx.reshape(-1), dy.reshape(-1)
        p = scores[(y[:, None] + dy).clamp(0, h - 1), (x[:, None] + dx).clamp(0, w - 1)]  # (M, (2r+1)^2)
        e = ((p - p.max(dim=1, keepdim=True).values) / self.conf["temperature"]).exp()
        off = (e @ torch.stack([dx, dy], 1).to(e.dtype)) / e.sum(dim=1, keepdim=True)
        xy = xy + off
        return xy, _bilinear(scores[None, None], xy, (h, w))[0]

    # ---------------------------------------------------------------- descriptors
    def describe(self, levels: list[torch.Tensor], xy: torch.Tensor, hw: tuple[int, int], b: int = 0) -> torch.Tensor:
        """(M,dim) unit descriptors of image ``b`` at ``xy`` (M,2) pixels: what bilinear sampling of the dense map
        (normalised per pixel, then renormalised) gives, computed at the four pixels around each point only."""
        h, w = hw
        x0 = xy[:, 0].floor().clamp(0, w - 1)
        y0 = xy[:, 1].floor().clamp(0, h - 1)
        fx, fy = xy[:, 0] - x0, xy[:, 1] - y0
        corners = [(x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)), (x0, y0 + 1, (1 - fx) * fy),
                   (x0 + 1, y0 + 1, fx * fy)]
        px = torch.cat([c[0] for c in corners]).clamp(max=w - 1)  # a corner past the edge has weight 0
        py = torch.cat([c[1] for c in corners]).clamp(max=h - 1)
        wt = torch.cat([c[2] for c in corners])
        full = levels[0].shape[-2:]
        feats = [levels[0][b, :, py.long(), px.long()]]  # (dim/4, 4M) at the pixels themselves
        for f in levels[1:]:  # the align-corners upsampling of each coarser level, at those pixels only
            feats.append(_bilinear(f[b:b + 1], torch.stack([px, py], 1), full))
        wd = self.head.weight[:-1, :, 0, 0]  # (dim, dim)
        d = F.normalize(wd @ torch.cat(feats, 0), dim=0)  # (dim, 4M): the dense map's unit vectors there
        d = (d * wt).reshape(self.dim, 4, -1).sum(1)
        return F.normalize(d, dim=0).t()

    def _forward(self, data: Mapping[str, Any]) -> dict[str, Any]:
        image = data["image"]
        hw = (int(image.shape[-2]), int(image.shape[-1]))
        levels = self.levels(image)
        if self.conf["dense"]:
            dmap, smap = self.dense_maps(levels, hw)
        else:
            dmap, smap = None, self.score_map(levels, hw)
        out: dict[str, Any] = {"scores_map": smap, "keypoints": [], "scores": [], "descriptors": []}
        for b in range(image.shape[0]):
            idx, _ = self.candidates(smap[b, 0])
            xy, sc = self.refine(smap[b, 0], idx)
            if dmap is not None:
                desc = F.normalize(_bilinear(dmap[b:b + 1], xy, hw), dim=0).t()
            else:
                desc = self.describe(levels, xy, hw, b)
            order = torch.argsort(sc, descending=True, stable=True)
            out["keypoints"].append(xy[order])
            out["scores"].append(sc[order])
            out["descriptors"].append(desc[order])
        return out


def _bilinear(maps: torch.Tensor, xy: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(1,C,h,w) maps sampled at ``xy`` (M,2), pixels of a ``size`` (H,W) grid whose corners align with the map's
    (align_corners: x = 0 and W-1 are the map's first and last columns) -> (C,M)."""
    hh, ww = size
    g = torch.stack([xy[:, 0] / max(ww - 1, 1), xy[:, 1] / max(hh - 1, 1)], 1) * 2 - 1
    return F.grid_sample(maps, g.view(1, 1, -1, 2).to(maps.dtype), mode="bilinear", align_corners=True)[0, :, 0]

