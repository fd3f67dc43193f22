"""Networks by name, one registry per family: detectors, keypoint extractors, place descriptors.

A config names a network (``alike-t``, ``yolox-nano``); the registry turns the name into the architecture, its
conf and, where the name stands for public pretrained weights, the function that converts them to our state
dict (``vslam/nn/weights/<source>.py``). Entries name their targets as ``"module:attr"`` strings imported on
first use, so listing the networks, or a config check that rejects an unknown name, imports no network code.

Adding a network: write the architecture (a ``BaseModel``), then one ``add`` line below; add a ``weights/``
module when it starts from a public checkpoint (docs/architecture.md, "how to add a network").
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Mapping

from vslam.errors import ConfigError

if TYPE_CHECKING:
    import torch


def _resolve(target: str) -> Any:
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class Entry:
    """``target``: "module:attr" of the architecture (a BaseModel subclass, or a function conf -> nn.Module);
    ``conf``: what this name sets over the architecture's defaults; ``weights``: "module:function" that returns
    our state dict for the built model (``function(model, source=None)``, reading the public file from
    ``source`` or its default place) or "" where there are no public weights; ``about``: one line for listings."""

    target: str
    conf: Mapping[str, Any] = field(default_factory=dict)
    weights: str = ""
    about: str = ""


class Registry:
    """The networks of one family by name."""

    def __init__(self, family: str):
        self.family = family
        self._entries: dict[str, Entry] = {}

    def add(self, name: str, target: str, conf: Mapping[str, Any] | None = None, weights: str = "",
            about: str = "") -> None:
        if name in self._entries:
            raise ValueError(f"{self.family} {name!r} is registered twice")
        self._entries[name] = Entry(target, dict(conf or {}), weights, about)

    def names(self) -> list[str]:
        return sorted(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def entry(self, name: str, field_name: str = "") -> Entry:
        """The entry of ``name``; an unknown name is one ConfigError line naming ``field_name`` and the known names."""
        if name not in self._entries:
            where = f"{field_name}: " if field_name else ""
            raise ConfigError(f"{where}unknown {self.family} {name!r} (known: {', '.join(self.names()) or 'none'})")
        return self._entries[name]

    def build(self, name: str, conf: Mapping[str, Any] | None = None, field_name: str = "") -> torch.nn.Module:
        """The architecture of ``name`` with the entry's conf, then ``conf``, over its defaults (random weights)."""
        e = self.entry(name, field_name)
        return _resolve(e.target)({**e.conf, **(conf or {})})  # a BaseModel refuses keys it does not know

    def pretrained(self, name: str, conf: Mapping[str, Any] | None = None, source: str | None = None,
                   field_name: str = "") -> torch.nn.Module:
        """``build(name, conf)`` with the public weights converted to our layout, strict, in eval mode."""
        from vslam.nn.checkpoint import load_state

        e = self.entry(name, field_name)
        if not e.weights:
            raise ConfigError(f"{field_name + ': ' if field_name else ''}{self.family} {name!r} has no public "
                              f"weights; give a checkpoint file")
        model = self.build(name, conf, field_name)
        convert: Callable[..., Mapping[str, torch.Tensor]] = _resolve(e.weights)
        state = convert(model, source)
        load_state(model, state, source or name, f"{name} weights")
        return model.eval()


DETECTORS = Registry("detector")
KEYPOINTS = Registry("keypoint extractor")
PLACES = Registry("place descriptor")
FAMILIES: dict[str, Registry] = {"detector": DETECTORS, "keypoints": KEYPOINTS, "place": PLACES}


def family(name: str) -> Registry:
    if name not in FAMILIES:
        raise ConfigError(f"unknown network family {name!r} (known: {', '.join(FAMILIES)})")
    return FAMILIES[name]


# The networks. Each public source converts its own checkpoint in vslam/nn/weights/<source>.py.
DETECTORS.add("yolox-nano", "vslam.nn.detectors.yolox:YOLOX", {"depth": 0.33, "width": 0.25},
              weights="vslam.nn.weights.yolox:convert", about="YOLOX-nano (Megvii, COCO, Apache-2.0)")
DETECTORS.add("yolox-nano-masks", "vslam.nn.detectors.yolox_masks:YOLOXMasks", {"depth": 0.33, "width": 0.25},
              about="YOLOX-nano with a box-prompted instance-mask head (trained here: vslam train yolox-masks)")
KEYPOINTS.add("alike-t", "vslam.nn.keypoints.alike:ALIKE", {"variant": "t"}, weights="vslam.nn.weights.alike:convert",
              about="ALIKE-t (Zhao et al., BSD-3-Clause), 64-d")
KEYPOINTS.add("alike-s", "vslam.nn.keypoints.alike:ALIKE", {"variant": "s"}, weights="vslam.nn.weights.alike:convert",
              about="ALIKE-s, 96-d")
KEYPOINTS.add("alike-n", "vslam.nn.keypoints.alike:ALIKE", {"variant": "n"}, weights="vslam.nn.weights.alike:convert",
              about="ALIKE-n, 128-d")
