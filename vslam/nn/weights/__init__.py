"""Public pretrained weights converted to our architectures, one module per source.

Each module reads the published file (a state dict, an ONNX graph's initializers) from
``<data>/pretrained/<source>/`` or a path given, maps its tensors onto our layer names and returns our state
dict; ``vslam.nn.registry`` names the function beside the architecture. Nothing here touches the network: the
files are read where they lie. A test per module proves the loaded network reproduces the source's outputs.
"""

from __future__ import annotations

from pathlib import Path

from vslam.errors import ConfigError


def pretrained_file(source: str | Path | None, *default: str) -> Path:
    """``source`` when given, else ``<data root>/pretrained/<default...>``; a missing file is one ConfigError line
    saying where the public weights are expected."""
    from vslam.paths import data_root

    p = Path(source) if source else data_root().joinpath("pretrained", *default)
    if not p.is_file():
        raise ConfigError(f"{p}: public weights not found (they come with the shared data, pretrained/"
                          f"{'/'.join(default)}; set VSLAM_DATA or give the file)")
    return p
