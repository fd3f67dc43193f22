"""Where the networks run: one rule for ConvPoint, the detector and VLADNet (torch only, no SLAM back end)."""

from __future__ import annotations

import torch

from vslam.errors import ConfigError


def pick_device(name: str, field: str) -> torch.device:
    """"auto": CUDA when torch sees a GPU, else the CPU; "cuda" without a GPU is a config error naming ``field``."""
    if name not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"{field} must be auto, cpu or cuda, got {name!r}")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{field}: cuda requested but torch sees no CUDA device")
    return torch.device("cuda" if name != "cpu" and torch.cuda.is_available() else "cpu")
