"""ALIKE's public checkpoints (Shiaoming/ALIKE, BSD-3-Clause) onto ``vslam.nn.keypoints.alike.ALIKE``.

The published files are plain state dicts of their ``ALNet``: ``block1`` (two conv + BN), ``block2..4``
(residual blocks with a ``downsample`` 1x1 skip), ``conv1..4`` (the level projections) and ``convhead2`` (the
head). Every tensor is mapped by name, strictly: a tensor left over, one missing or one of another shape is one
``ConfigError`` line naming the file (a checkpoint of another variant says so instead of loading half).
"""

from __future__ import annotations

from pathlib import Path

import torch

from vslam.errors import ConfigError
from vslam.nn.checkpoint import read_checkpoint
from vslam.nn.weights import pretrained_file

_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def key_map() -> dict[str, str]:
    """Public name -> our name, for every tensor of a single-head ALIKE (t, s, n)."""
    m: dict[str, str] = {}
    for j, (conv, bn) in enumerate((("conv1", "bn1"), ("conv2", "bn2"))):
        m[f"block1.{conv}.weight"] = f"stem.{3 * j}.weight"  # stem: conv, bn, relu, conv, bn, relu
        m.update({f"block1.{bn}.{k}": f"stem.{3 * j + 1}.{k}" for k in _BN})
    for i in (2, 3, 4):
        for j, (conv, bn) in enumerate((("conv1", "bn1"), ("conv2", "bn2"))):
            m[f"block{i}.{conv}.weight"] = f"enc{i}.body.{3 * j}.weight"  # body: conv, bn, relu, conv, bn
            m.update({f"block{i}.{bn}.{k}": f"enc{i}.body.{3 * j + 1}.{k}" for k in _BN})
        m[f"block{i}.downsample.weight"] = f"enc{i}.skip.weight"
        m[f"block{i}.downsample.bias"] = f"enc{i}.skip.bias"
    for i in range(4):
        m[f"conv{i + 1}.weight"] = f"proj.{i}.weight"
    m["convhead2.weight"] = "head.weight"
    return m


def convert(model: torch.nn.Module, source: str | Path | None = None) -> dict[str, torch.Tensor]:
    """Our state dict for ``model`` (an ALIKE of some variant) from the public ``alike-<variant>.pth`` (or the file
    ``source``)."""
    variant = model.conf["variant"]
    path = pretrained_file(source, "alike", f"alike-{variant}.pth")
    theirs = read_checkpoint(path, f"ALIKE-{variant} state dict")
    names = key_map()
    extra = [k for k in theirs if k not in names]
    if extra:
        raise ConfigError(f"{path}: not an ALIKE t/s/n state dict: unexpected tensor {extra[0]!r}"
                          + (f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""))
    want = model.state_dict()
    out: dict[str, torch.Tensor] = {}
    for k, ours in names.items():
        if k not in theirs:
            raise ConfigError(f"{path}: not an ALIKE t/s/n state dict: no {k!r}")
        t = theirs[k]
        if tuple(t.shape) != tuple(want[ours].shape):
            raise ConfigError(f"{path}: {k!r} is {tuple(t.shape)}, ALIKE-{variant} expects {tuple(want[ours].shape)} "
                              f"(a checkpoint of another variant?)")
        out[ours] = t
    return out
