"""Checkpoints of the networks trained here, read safely.

``read_checkpoint`` is the one place a torch file is opened: ``torch.load(weights_only=True)`` only, so a
weights path from a config or a ``last.pt`` found in an output folder can never run code (a pickle may name
any callable; the weights-only unpickler accepts tensors and plain containers and refuses the rest). A file that
cannot be read that way, or is a checkpoint of another kind, is one ``ConfigError`` line naming the file and
what was expected; there is no fallback to the full unpickler. ``reading`` gives the same one line for errors
while the loaded dict is applied, and ``load_state`` applies a state dict: weights of another shape than the
network (a checkpoint for another number of classes, width or descriptor size) are one line naming the file, the
first parameter that does not fit, its shape in the file and the shape the network expects, not torch's
"Error(s) in loading state_dict".

Networks of the registry (``vslam.nn.registry``) are saved with ``save_model`` as ``{arch, conf, state_dict,
meta}`` and rebuilt by ``load_model``. The older networks trained here still use their own dicts: ConvPoint and
VLADNet ``{config, state_dict, meta}`` (``save_weights`` / ``load_weights``), the from-scratch detector
``{model, config, names}`` (``vslam.dynamic.detector``). Only torch is
imported, so the GPU machine (no gtsam / pycolmap) can train and load them.
"""

from __future__ import annotations

import contextlib
import pickle
import re
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import torch


def _first(text: str, limit: int = 160) -> str:
    """The first line of an exception text, cut at its first sentence when long (torch's run on for a paragraph)."""
    line = text.strip().splitlines()[0] if text.strip() else ""
    if len(line) > limit and ". " in line:
        line = line[:line.index(". ")]
    return line[:limit]


def _reason(e: BaseException) -> str:
    """Why torch could not read a file, in a few words. The weights-only unpickler wraps its own error (which
    names the refused global) in a page of advice that ends in 'use weights_only=False': keep only the former."""
    inner = e.__context__
    if isinstance(e, pickle.UnpicklingError) and isinstance(inner, pickle.UnpicklingError):
        m = re.search(r"GLOBAL (\S+)", str(inner))
        if m:
            return f"it holds Python objects ({m.group(1)}) that are never unpickled: that could run code"
        return f"not a torch.save file of tensors and plain types: {_first(str(inner))}"
    if isinstance(e, EOFError):
        return "empty or truncated file"
    return f"{type(e).__name__}: {_first(str(e))}" if str(e) else type(e).__name__


def _message(path: Path, what: str, reason: str, note: str) -> str:
    return f"{path}: not a {what} ({reason})" + (f"; {note}" if note else "")


@contextlib.contextmanager
def reading(path: str | Path, what: str, note: str = "") -> Iterator[None]:
    """Errors inside (other than VslamErrors, already one line) -> ``ConfigError("<path>: not a <what> (<why>)")``
    with ``; <note>`` appended when given (e.g. "resume refused")."""
    from vslam.errors import ConfigError, VslamError

    try:
        yield
    except VslamError:
        raise
    except Exception as e:
        raise ConfigError(_message(Path(path), what, _reason(e), note)) from None


def read_checkpoint(path: str | Path, what: str, keys: Sequence[str] = (), map_location: str | torch.device = "cpu",
                    note: str = "") -> dict:
    """The dict ``torch.save``d at ``path``, loaded weights-only. ``what`` names the expected kind ("detector
    checkpoint"), ``keys`` the entries it must have; either failing, or the file missing, damaged or holding
    other objects than tensors and plain types, is one ``ConfigError`` line naming the file."""
    from vslam.errors import ConfigError

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: {what} not found" + (f"; {note}" if note else ""))
    with reading(p, what, note), warnings.catch_warnings():
        # a bare pickle of a newer protocol draws a multi-line warning from torch before it is refused
        warnings.filterwarnings("ignore", message="Detected pickle protocol", category=UserWarning)
        ck = torch.load(p, map_location=map_location, weights_only=True)
    if not isinstance(ck, dict):
        raise ConfigError(_message(p, what, f"a {type(ck).__name__}, not a dict", note))
    missing = [k for k in keys if k not in ck]
    if missing:
        has = ", ".join(str(k) for k in list(ck)[:8]) or "nothing"
        raise ConfigError(_message(p, what, f"no {', '.join(missing)}; it holds {has}", note))
    return ck


def _shape(t: Any) -> str:
    return "(" + ", ".join(str(int(n)) for n in t.shape) + ")" if isinstance(t, torch.Tensor) else f"a {type(t).__name__}"


def misfit(model: torch.nn.Module, state: Any) -> str | None:
    """Why ``state`` cannot be loaded into ``model`` strictly -- the first parameter (in the network's order) whose
    shape differs, else the first one missing from the file, else the first the network lacks -- or None."""
    if not isinstance(state, Mapping):
        return f"its weights are a {type(state).__name__}, not a dict of tensors"
    want = model.state_dict()
    for k, w in want.items():
        if k in state and (not isinstance(state[k], torch.Tensor) or state[k].shape != w.shape):
            return f"'{k}' is {_shape(state[k])} in the file, the network expects {_shape(w)}"
    missing = [k for k in want if k not in state]
    extra = [str(k) for k in state if k not in want]

    def more(names: list[str]) -> str:
        return f" (and {len(names) - 1} more)" if len(names) > 1 else ""

    if missing:
        return f"the file has no '{missing[0]}'{more(missing)}" + (f"; it has '{extra[0]}'{more(extra)} instead" if extra else "")
    if extra:
        return f"the file has '{extra[0]}'{more(extra)}, which the network lacks"
    return None


def load_state(model: torch.nn.Module, state: Any, path: str | Path, what: str, note: str = "",
               looks_like: Callable[[Mapping[str, Any]], str] | None = None) -> None:
    """``model.load_state_dict(state)`` (strict). Weights that do not fit the network are one ``ConfigError``
    line: "<path>: <what> does not fit the network: '<param>' is (80, 64, 1, 1) in the file, the network expects
    (2, 64, 1, 1)", followed by ``looks_like(state)`` (what the file's tensors look like they were made for) when
    given and by ``; <note>``."""
    from vslam.errors import ConfigError

    why = misfit(model, state)
    if why is not None:
        hint = ""
        if looks_like is not None and isinstance(state, Mapping):
            try:
                hint = looks_like(state)
            except Exception:  # a hint only: a state too odd to describe gets none
                hint = ""
        raise ConfigError(f"{Path(path)}: {what} does not fit the network: {why}" + (f" ({hint})" if hint else "")
                          + (f"; {note}" if note else ""))
    with reading(path, what, note):
        model.load_state_dict(state)


def save_weights(model: torch.nn.Module, config: dict, path: str | Path, meta: dict | None = None) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"config": config, "state_dict": model.state_dict(), "meta": meta or {}}, p)
    return p


def load_weights(path: str | Path, name: str, command: str, build: Callable[[dict], torch.nn.Module],
                 looks_like: Callable[[Mapping[str, Any]], str] | None = None) -> torch.nn.Module:
    """The network ``build(config)`` with the file's weights, eval mode, CPU. ``name`` and ``command`` (how to
    train it) go into the error; ``looks_like``: see ``load_state``."""
    from vslam.errors import ConfigError

    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{p}: {name} weights not found (train them with `{command}`)")
    what = f"{name} checkpoint"
    ck = read_checkpoint(p, what, ("config", "state_dict"))
    with reading(p, what):
        model = build(ck["config"])
    load_state(model, ck["state_dict"], p, what, looks_like=looks_like)
    return model.eval()


# The one format of the networks in the registry (vslam.nn.registry): what rebuilds the network (``arch``, the
# registry name, and ``conf``, its merged conf), its weights and ``meta`` (source, licence, data, the training's
# numbers). Training checkpoints add their own keys (optimiser, progress) beside these.
FORMAT_KEYS = ("arch", "conf", "state_dict", "meta")


def save_model(model: torch.nn.Module, path: str | Path, arch: str, meta: dict | None = None, half: bool = False,
               **extra: Any) -> Path:
    """Write ``{arch, conf, state_dict, meta, **extra}`` atomically (an interrupted save leaves the old file).
    ``half``: floating tensors stored as float16 (loading casts back to float32)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.half() if half and v.is_floating_point() else v for k, v in model.state_dict().items()}
    tmp = p.with_suffix(p.suffix + ".tmp")
    torch.save({"arch": arch, "conf": dict(getattr(model, "conf", {})), "state_dict": state, "meta": meta or {},
                **extra}, tmp)
    tmp.replace(p)
    return p


def load_model(path: str | Path, registry: Any, field_name: str = "") -> tuple[torch.nn.Module, dict]:
    """The network a ``save_model`` file describes, built through ``registry`` (a ``vslam.nn.registry.Registry``)
    with the file's weights (float32), eval mode, CPU -> (model, the file's dict). A file of another family or
    format, or weights that do not fit, is one ConfigError line naming the file."""
    from vslam.errors import ConfigError

    what = f"{registry.family} checkpoint"
    note = f"set by {field_name}" if field_name else ""
    ck = read_checkpoint(path, what, FORMAT_KEYS, note=note)
    if ck["arch"] not in registry:
        raise ConfigError(_message(Path(path), what, f"its network {ck['arch']!r} is not a {registry.family} "
                                   f"(known: {', '.join(registry.names())})", note))
    with reading(path, what, note):
        model = registry.build(ck["arch"], ck["conf"])
        state = {k: v.float() if v.is_floating_point() else v for k, v in ck["state_dict"].items()}
    load_state(model, state, path, what, note=note)
    return model.eval(), ck
