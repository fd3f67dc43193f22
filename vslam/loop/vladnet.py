"""VLADNet: a small CNN + NetVLAD layer as the learned place descriptor (seed 003's "VLADNet").

NetVLAD (Arandjelović et al., CVPR 2016): local features x_i (D,) of a conv map are softly assigned to K
learned clusters, a_k(x_i) = softmax_k(w_k . x_i + b_k); the descriptor is V_k = sum_i a_k(x_i) (x_i - c_k),
intra-normalised per cluster, flattened (K*D), L2-normalised. A learned linear projection to ``out_dim``
then L2 stands in for NetVLAD's PCA + whitening (trained with the rest). Clusters start at k-means centres of
the backbone's features (``init_clusters``), w_k = 2 alpha c_k, b_k = -alpha |c_k|^2 as in the paper.

The backbone is ours and small (4 stages of two 3x3 convs, stride 16, ~0.2 M parameters): the input is the
grey image resized to ``input_size`` and standardised per image (zero mean, unit std), which removes a global
gain / offset change before the network sees it. torch + numpy + cv2 only, so it trains on the GPU machine too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F


@dataclass(frozen=True)
class VladNetConfig:
    channels: tuple[int, ...] = (16, 32, 64, 96)
    clusters: int = 16
    out_dim: int = 256
    input_size: tuple[int, int] = (160, 120)  # (width, height) the image is resized to
    alpha: float = 10.0  # soft-assignment sharpness at initialisation


def _stage(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, 2, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class NetVLAD(nn.Module):
    """(B,D,H,W) features -> (B,K*D) intra-normalised, L2-normalised VLAD vectors."""

    def __init__(self, dim: int, clusters: int, alpha: float = 10.0):
        super().__init__()
        self.alpha = alpha
        self.assign = nn.Conv2d(dim, clusters, 1, bias=True)
        self.centroids = nn.Parameter(torch.randn(clusters, dim) * 0.1)

    @torch.no_grad()
    def init_clusters(self, centres: torch.Tensor) -> None:
        """Centres (K,D) from k-means on backbone features of training images (L2-normalised features)."""
        self.centroids.copy_(centres)
        self.assign.weight.copy_((2.0 * self.alpha * centres)[:, :, None, None])
        self.assign.bias.copy_(-self.alpha * centres.pow(2).sum(dim=1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.normalize(x, dim=1)  # descriptor-wise L2 first (the paper's input normalisation)
        a = F.softmax(self.assign(x), dim=1).flatten(2)  # (B,K,N)
        f = x.flatten(2)  # (B,D,N)
        # V[b,k,:] = sum_n a[b,k,n] (f[b,:,n] - c_k)
        v = torch.einsum("bkn,bdn->bkd", a, f) - a.sum(dim=2, keepdim=True) * self.centroids[None]
        v = F.normalize(v, dim=2)
        return F.normalize(v.flatten(1), dim=1)


class VladNet(nn.Module):
    """(B,1,H,W) standardised grey images -> (B,out_dim) unit descriptors."""

    def __init__(self, cfg: VladNetConfig = VladNetConfig()):
        super().__init__()
        self.cfg = cfg
        chans = (1, *cfg.channels)
        self.backbone = nn.Sequential(*[_stage(a, b) for a, b in zip(chans[:-1], chans[1:])])
        self.vlad = NetVLAD(chans[-1], cfg.clusters, cfg.alpha)
        self.project = nn.Linear(cfg.clusters * chans[-1], cfg.out_dim)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.backbone(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.project(self.vlad(self.backbone(x))), dim=1)


def preprocess(images: list[np.ndarray] | np.ndarray, size: tuple[int, int]) -> torch.Tensor:
    """uint8 images (grey or BGR, any size) -> (B,1,h,w) float32, each standardised to zero mean / unit std."""
    out = []
    for im in images:
        g = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im
        if (g.shape[1], g.shape[0]) != tuple(size):
            g = cv2.resize(g, tuple(size), interpolation=cv2.INTER_AREA)
        g = g.astype(np.float32)
        out.append((g - g.mean()) / max(float(g.std()), 1.0))
    return torch.from_numpy(np.stack(out)[:, None])


def save_vladnet(model: VladNet, path: str | Path, meta: dict | None = None) -> Path:
    from vslam.nn.checkpoint import save_weights

    cfg = model.cfg
    return save_weights(model, {"channels": list(cfg.channels), "clusters": cfg.clusters, "out_dim": cfg.out_dim,
                                "input_size": list(cfg.input_size), "alpha": cfg.alpha}, path, meta)


def load_vladnet(path: str | Path) -> VladNet:
    """Weights from a local file (never the network); eval mode, CPU."""
    from vslam.nn.checkpoint import load_weights

    return load_weights(path, "VLADNet", "vslam train place", lambda c: VladNet(VladNetConfig(
        tuple(c["channels"]), int(c["clusters"]), int(c["out_dim"]), tuple(c["input_size"]), float(c["alpha"]))))


class VladNetDescriptor:
    """``PlaceDescriptor`` from the image alone (keypoints unused). One image per call, batched describe_many.
    ``device`` "auto": CUDA when torch sees a GPU (descriptors equal up to float rounding)."""

    def __init__(self, model: VladNet, threads: int = 0, device: str | torch.device = "auto"):
        from vslam.nn.device import pick_device

        self.device = pick_device(device, "loop.device") if isinstance(device, str) else device
        self.model = model.eval().to(self.device)
        self.dim = model.cfg.out_dim
        self.threads = threads

    @classmethod
    def from_file(cls, path: str | Path, device: str = "auto") -> VladNetDescriptor:
        return cls(load_vladnet(path), device=device)

    @torch.no_grad()
    def describe_many(self, images: list[np.ndarray], batch: int = 32) -> np.ndarray:
        out = []
        for i in range(0, len(images), batch):
            x = preprocess(images[i:i + batch], self.model.cfg.input_size).to(self.device)
            out.append(self.model(x).cpu().numpy())
        return np.concatenate(out).astype(np.float32) if out else np.zeros((0, self.dim), np.float32)

    def describe(self, image: np.ndarray | None, features=None) -> np.ndarray:
        if image is None:
            return np.zeros(self.dim, np.float32)
        return self.describe_many([image])[0]
