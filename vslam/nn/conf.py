"""Network confs: a default merged with what a config or checkpoint gives (no torch import: configs are checked
before any network is built)."""

from __future__ import annotations

import copy
from typing import Any, Mapping

from vslam.errors import ConfigError


def merge_conf(default: Mapping[str, Any], conf: Mapping[str, Any], where: str) -> dict[str, Any]:
    """``default`` updated by ``conf``, recursively for dict values; a key of ``conf`` that ``default`` lacks is a
    ConfigError "<where>: unknown key 'x' (known: a, b)", so a typo never silently falls back to a default."""
    out = copy.deepcopy(dict(default))
    for k, v in conf.items():
        if k not in out:
            raise ConfigError(f"{where}: unknown key {k!r} (known: {', '.join(sorted(out)) or 'none'})")
        if isinstance(out[k], dict) and isinstance(v, Mapping):
            out[k] = merge_conf(out[k], v, f"{where}.{k}")
        else:
            out[k] = copy.deepcopy(v)
    return out
