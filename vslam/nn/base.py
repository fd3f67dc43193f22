"""The base of every network here: a default conf merged with the caller's, dict in and dict out.

The hloc / LightGlue convention: ``Model(conf)`` where ``conf`` may name any subset of ``default_conf`` (nested
dicts merge key by key; an unknown key is a ``ConfigError`` naming it and the known ones, so a typo in a config
never silently falls back to a default), and ``model(data)`` with ``data`` a dict holding at least
``required_inputs``. Each subclass documents the shapes of its inputs and outputs in its docstring; the dict
keeps call sites readable when a network grows an output (a mask head, a sparse descriptor head) without a
change of signature for every caller.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

import torch

from vslam.nn.conf import merge_conf


class BaseModel(torch.nn.Module):
    """Subclasses set ``default_conf`` and ``required_inputs`` and implement ``_init(conf)`` (build the layers)
    and ``_forward(data) -> dict``. ``self.conf`` is the merged conf: what a checkpoint stores to rebuild it."""

    default_conf: ClassVar[dict[str, Any]] = {}
    required_inputs: ClassVar[tuple[str, ...]] = ()

    def __init__(self, conf: Mapping[str, Any] | None = None):
        super().__init__()
        self.conf = merge_conf(self.default_conf, conf or {}, type(self).__name__)
        self._init(self.conf)

    def _init(self, conf: dict[str, Any]) -> None:
        raise NotImplementedError

    def _forward(self, data: Mapping[str, Any]) -> dict[str, Any]:
        raise NotImplementedError

    def forward(self, data: Mapping[str, Any]) -> dict[str, Any]:
        missing = [k for k in self.required_inputs if k not in data]
        if missing:  # a programming error, not a user's: the caller built the dict
            raise KeyError(f"{type(self).__name__} needs inputs {', '.join(missing)}; got {', '.join(data) or 'none'}")
        return self._forward(data)
