"""Weights files of the networks trained here (ConvPoint, VLADNet): one ``torch.save`` dict of ``config``
(what rebuilds the network), ``state_dict`` and ``meta`` (the training's numbers). Read from local files only;
a missing, damaged or foreign file is one line naming it, not torch's traceback. Only torch is imported, so the
GPU machine (no gtsam / pycolmap) can train and load them."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch


def save_weights(model: torch.nn.Module, config: dict, path: str | Path, meta: dict | None = None) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"config": config, "state_dict": model.state_dict(), "meta": meta or {}}, p)
    return p


def load_weights(path: str | Path, name: str, command: str, build: Callable[[dict], torch.nn.Module]) -> torch.nn.Module:
    """The network ``build(config)`` with the file's weights, eval mode, CPU. ``name`` and ``command`` (how to
    train it) go into the error."""
    from vslam.errors import ConfigError

    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{p}: {name} weights not found (train them with `{command}`)")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=True)
        model = build(ck["config"])
        model.load_state_dict(ck["state_dict"])
    except Exception as e:  # a damaged or foreign file
        raise ConfigError(f"{p}: not a {name} checkpoint ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    return model.eval()
