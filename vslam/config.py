"""Typed configs: frozen dataclasses with defaults, overridden by YAML.

An unknown key, a key given twice, or a value of the wrong type is a
ConfigError naming the key and the file (and its line), so a typo never silently falls back
to a default. A mistake in a ``--set KEY=VALUE`` names that --set instead: the overrides ``parse_overrides``
makes remember where each key came from (``Overrides``), and ``deep_merge`` keeps that.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

import yaml

from vslam.errors import ConfigError
from vslam.resources import resolve_config

C = TypeVar("C")

# With ``nonnegative``, the numbers that may still be negative (a clock offset has a sign; every count,
# threshold, size and time of the SLAM config has none).
SIGNED_FIELDS = frozenset({"t_offset_s"})


class Overrides(dict):  # type: ignore[type-arg]
    """A nested override dict (``parse_overrides``) that remembers where its keys came from: ``origins`` maps a
    dotted key ("slam.features.n_features") to the text an error about it starts with ("--set
    slam.features.n_features=abc"). Otherwise a plain dict; ``deep_merge`` carries the origins along."""

    def __init__(self, data: Mapping[str, Any] = (), origins: Mapping[str, str] | None = None):  # type: ignore[assignment]
        super().__init__(data)
        self.origins: dict[str, str] = dict(origins or {})


yaml.SafeDumper.add_representer(Overrides, yaml.SafeDumper.represent_dict)  # dumped as the plain dict it is
yaml.Dumper.add_representer(Overrides, yaml.Dumper.represent_dict)


def _parent(key: str) -> str:
    """'a.b[2]' -> 'a.b', 'a.b' -> 'a', 'a' -> ''."""
    cut = max(key.rfind("."), key.rfind("["))
    return key[:cut] if cut > 0 else ""


def _under(key: str, top: str) -> bool:
    """``key`` is ``top`` or inside it."""
    return key == top or key.startswith((top + ".", top + "["))


def _where(source: str, name: str, origins: Mapping[str, str] | None) -> str:
    """What an error about key ``name`` starts with: the origin of it or of the nearest key above it that has
    one ("--set a.b=c", "file.yaml:12"), else ``source``."""
    key = name
    while origins and key:
        if key in origins:
            return origins[key]
        key = _parent(key)
    return source


def from_dict(cls: type[C], data: dict[str, Any] | None, source: str = "<config>", prefix: str = "",
              nonnegative: bool = False, origins: Mapping[str, str] | None = None) -> C:
    """Build dataclass ``cls`` from a (nested) dict; missing keys keep their defaults.

    ``nonnegative``: every number must be finite and >= 0 (but ``SIGNED_FIELDS``), so that ``n_features=-100``
    is a config error naming the key, not an OpenCV assertion deep inside a run.
    ``origins``: dotted key -> where it came from ("--set a.b=1", "cfg.yaml:3"), which an error about that key
    names instead of ``source``; default: those of ``data`` when it is an ``Overrides``."""
    if origins is None:
        origins = getattr(data, "origins", None)
    data = data or {}
    if not isinstance(data, dict):
        where = _where(source, prefix.rstrip("."), origins)
        raise ConfigError(f"{where}: '{prefix.rstrip('.') or 'top level'}' must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in fields:
            from vslam.runtime import MOVED_KEYS

            if name in MOVED_KEYS:
                raise ConfigError(f"{_where(source, name, origins)}: '{name}' is '{MOVED_KEYS[name]}' now")
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{_where(source, name, origins)}: unknown key '{name}' (known: {known})")
        kwargs[key] = _coerce(hints[key], value, source, name, nonnegative, origins)
    try:
        return cls(**kwargs)
    except ConfigError as e:  # a __post_init__ check: say where the config came from
        msg = str(e)
        if msg.startswith(source) or any(msg.startswith(w) for w in (origins or {}).values()):
            raise
        # the key the check names: one given by an override before one from the file
        named = [_where(source, f"{prefix}{k}", origins) for k in data if re.search(rf"\b{re.escape(str(k))}\b", msg)]
        named.sort(key=lambda w: w.startswith(source))
        raise ConfigError(f"{named[0] if named else source}: {e}") from None


def _coerce(tp: Any, value: Any, source: str, name: str, nonnegative: bool = False,
            origins: Mapping[str, str] | None = None) -> Any:
    origin = typing.get_origin(tp)
    where = _where(source, name, origins)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, source, prefix=f"{name}.", nonnegative=nonnegative, origins=origins or {})
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, value, source, name, nonnegative, origins)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: bad value for '{name}'")
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ConfigError(f"{where}: '{name}' must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: '{name}' must be a list, got {value!r}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:  # fixed-length tuple[A, B, ...]
            if len(value) != len(args):
                raise ConfigError(f"{where}: '{name}' must have {len(args)} items, got {value!r}")
            return tuple(_coerce(a, v, source, f"{name}[{i}]", nonnegative, origins)
                         for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        items = [_coerce(item, v, source, f"{name}[{i}]", nonnegative, origins) if item is not Any else v
                 for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 5e-5 (no dot) as text; it is a number here
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: '{name}' must be a number, got {value!r}")
        return _check_sign(float(value), where, name, nonnegative)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: '{name}' must be an integer, got {value!r}")
        return _check_sign(value, where, name, nonnegative)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: '{name}' must be true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: '{name}' must be a string, got {value!r}")
        return value
    return value


_FLOAT_TEXT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")


def _check_sign(value: int | float, source: str, name: str, nonnegative: bool) -> int | float:
    if nonnegative and name.rsplit(".", 1)[-1].split("[")[0] not in SIGNED_FIELDS:
        if not math.isfinite(value) or value < 0:
            raise ConfigError(f"{source}: '{name}' must be a finite number >= 0, got {value!r}")
    return value


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a mapping key given twice (PyYAML keeps the last one silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)  # type: ignore[no-untyped-call]
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice (first on line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, where: str) -> Any:
    """YAML text -> data; a syntax error or a duplicate key is a ConfigError naming ``where`` and the line."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f"{where}:{mark.line + 1}" if mark is not None and where.endswith((".yaml", ".yml")) else where
        raise ConfigError(f"{at}: invalid YAML ({getattr(e, 'problem', None) or e})") from None


def load_yaml(path: str | Path) -> dict[str, Any]:
    """A YAML mapping from a file, or from a preset named instead of a file (``vslam.resources.resolve_config``)."""
    path = resolve_config(path)
    if not path.is_file():
        hint = " (nor a preset: `vslam presets` lists them)" if len(path.parts) == 1 else ""
        raise ConfigError(f"{path}: config file not found{hint}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({e})") from None
    data = parse_yaml(text, str(path))
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: a config must be a mapping of sections, got {type(data).__name__}")
    return data or {}


def key_lines(path: str | Path, text: str) -> dict[str, str]:
    """Dotted key ("slam.features.n_features", "dataset.drop[0]") -> "<path>:<line>" of a YAML text's keys and
    list items; {} when the text does not parse."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    out: dict[str, str] = {}

    def walk(node: Any, key: str) -> None:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    sub = f"{key}.{k.value}" if key else str(k.value)
                    out[sub] = f"{path}:{k.start_mark.line + 1}"
                    walk(v, sub)
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                out[f"{key}[{i}]"] = f"{path}:{v.start_mark.line + 1}"
                walk(v, f"{key}[{i}]")

    walk(root, "")
    return out


def _leaves(d: Mapping[str, Any], key: str = "") -> list[str]:
    """Dotted keys of the values in a nested dict that are not dicts (what ``deep_merge`` replaces)."""
    out: list[str] = []
    for k, v in d.items():
        sub = f"{key}.{k}" if key else str(k)
        out += _leaves(v, sub) if isinstance(v, dict) else [sub]
    return out


def load_config(cls: type[C], path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                nonnegative: bool = False) -> C:
    """Defaults <- YAML file or preset <- overrides (a nested dict, e.g. from --set a.b=c).

    A bad value or unknown key is a ConfigError naming where it came from: the --set that gave it (when
    ``overrides`` is an ``Overrides``), else the file and the key's line."""
    path = resolve_config(path) if path else None
    data: dict[str, Any] = load_yaml(path) if path else {}
    origins = key_lines(path, path.read_text()) if path else {}
    if overrides:
        data = deep_merge(data, overrides)
        replaced = _leaves(overrides)  # a file's line no longer says where these came from
        origins = {k: w for k, w in origins.items() if not any(_under(k, r) for r in replaced)}
        origins.update(getattr(overrides, "origins", {}))
    return from_dict(cls, data, str(path) if path else "<defaults>", nonnegative=nonnegative, origins=origins)


def deep_merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """``a`` with ``b``'s values over it, dicts merged key by key; an ``Overrides`` when either is one (the
    origins of ``a``'s keys that ``b`` replaces are dropped)."""
    out = dict(a)
    for k, v in b.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    oa, ob = getattr(a, "origins", {}), getattr(b, "origins", {})
    if not (oa or ob):
        return out
    replaced = _leaves(b)
    kept = {k: w for k, w in oa.items() if not any(_under(k, r) for r in replaced)}
    return Overrides(out, {**kept, **ob})


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """['a.b=1', 'c=x'] -> {'a': {'b': 1}, 'c': 'x'}; values parsed as YAML scalars. An ``Overrides``: an error
    about a key one of them gave names that --set."""
    out = Overrides()
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        key, raw = item.split("=", 1)
        node = out
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"--set {item!r}: empty key part in {key!r}")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p!r} was given a value by an earlier --set")
        node[parts[-1]] = parse_yaml(raw, f"--set {item}")
        dotted = ".".join(parts)
        out.origins = {k: w for k, w in out.origins.items() if not _under(k, dotted)}  # a later --set replaces it
        out.origins[dotted] = f"--set {item}"
    return out


def to_dict(cfg: Any) -> dict[str, Any]:
    """Dataclass -> plain dict (tuples as lists) for writing the resolved config beside outputs."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v

    return conv(cfg)
