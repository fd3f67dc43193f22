"""Files shipped inside the package: presets (pipeline configs chosen by name) and the default weights.

They are package data (``vslam/presets/*.yaml``, ``vslam/models/``), so a source checkout, an editable
install and a wheel installed anywhere find them the same way. Weights that no preset or default loads
(experiments, ablations) stay in the repository's ``models/`` and out of the wheel.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from vslam.errors import ConfigError, VslamError

PRESET_SUFFIX = ".yaml"


def _package_dir(name: str) -> Path:
    d = resources.files("vslam") / name
    if not isinstance(d, Path):  # torch, OpenCV and numpy open files by path, not through a zip reader
        raise VslamError(f"vslam is imported from an archive ({d}); its presets and weights need an unpacked install")
    return d


def presets_dir() -> Path:
    return _package_dir("presets")


def preset_names() -> list[str]:
    return sorted(p.stem for p in presets_dir().glob(f"*{PRESET_SUFFIX}"))


def preset_path(name: str) -> Path:
    """The YAML of preset ``name`` (``tum_rgbd``); an unknown name is a ConfigError listing the presets."""
    p = presets_dir() / f"{name}{PRESET_SUFFIX}"
    if not p.is_file():
        raise ConfigError(f"unknown preset {name!r} (presets: {', '.join(preset_names())}; or give a config file)")
    return p


def preset_description(name: str) -> str:
    """What the preset runs, in one line: its leading comment up to the first '.', ':' or ';' outside
    parentheses (the rest of the comment says how and why)."""
    lines = []
    for line in preset_path(name).read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    text = " ".join(lines) + " "
    depth = 0
    for i, ch in enumerate(text[:-1]):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and ch in ".:;" and text[i + 1] == " ":
            return text[:i]
    return text.strip()


def resolve_config(path: str | Path) -> Path:
    """A config argument -> the file to read: an existing file as given; else a preset name (``tum_rgbd``,
    ``tum_rgbd.yaml``); else ``<anything>/configs/<preset>.yaml``, where the presets lived before they became
    package data (scripts, bench suites and notes still name them so); else the path unchanged, for the
    reader's "not found"."""
    p = Path(path)
    if p.is_file():
        return p
    names = set(preset_names())
    bare = len(p.parts) == 1 and p.suffix in ("", PRESET_SUFFIX)
    if p.stem in names and (bare or (p.parent.name == "configs" and p.suffix == PRESET_SUFFIX)):
        return preset_path(p.stem)
    return p


def shipped_model(filename: str) -> Path:
    """A weights file shipped with the package (``convpoint_v1.pt``); its model card is in models/README.md
    of the repository."""
    return _package_dir("models") / filename
