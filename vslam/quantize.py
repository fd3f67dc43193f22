"""Post-training int8 quantisation of the convolutional networks for the CPU.

Why: on 2 CPU threads the networks are most of the learned pipeline's time. Integer convolutions (FBGEMM /
oneDNN, VNNI where the CPU has it) run the same layers several times faster; the keypoints and descriptors move
a little (``models/README.md``; docs/speed.md, 'Measurements behind settings in the code').

Scheme: PyTorch's FX graph-mode static quantisation (``torch.ao.quantization``, backend "x86"): weights int8 per
output channel (from the float weights, at load), activations uint8 per tensor with ranges chosen by a histogram
observer over calibration images (``calibrate``). Only those activation ranges are stored, in a small JSON file
beside the weights (``<weights>.int8.json``) with the weights file's SHA-256, so a retrained network cannot be
run with stale ranges; ``build`` rebuilds the quantised graph from the float network and the stored ranges,
without data. Modules named in ``float_modules`` stay float (the first convolution: it sees the raw
standardised image, where 8 bits cost most).

Only torch is imported (the GPU machine has no gtsam / pycolmap). Integer kernels are CPU-only: on CUDA the
networks keep float / bf16.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path
from typing import Iterable, Sequence

import torch
from torch import nn

QPARAM_SUFFIX = ".int8.json"


def _fx():
    """torch's FX quantisation API, or a one-line error where this torch build lacks it."""
    from vslam.errors import ConfigError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch >= 2.5 flags torch.ao.quantization for a future move
            from torch.ao.quantization import QConfig, QConfigMapping, get_default_qconfig_mapping
            from torch.ao.quantization.observer import MinMaxObserver, default_per_channel_weight_observer
            from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx
    except ImportError as e:  # pragma: no cover - depends on the torch build
        raise ConfigError(f"int8 inference needs torch.ao.quantization (FX), missing in torch {torch.__version__}: {e}") from None
    if "x86" not in torch.backends.quantized.supported_engines:  # pragma: no cover
        raise ConfigError(f"int8 inference: this torch build has no x86 quantised engine ({torch.backends.quantized.supported_engines})")
    return QConfig, QConfigMapping, get_default_qconfig_mapping, MinMaxObserver, default_per_channel_weight_observer, prepare_fx, convert_fx


def _mapping(observer: str, float_modules: Sequence[str]):
    QConfig, QConfigMapping, get_default, MinMax, per_channel, _, _ = _fx()
    qm = get_default("x86")  # histogram activations (reduced range), per-channel weights
    if observer == "minmax":
        qm = QConfigMapping().set_global(QConfig(activation=MinMax.with_args(reduce_range=True), weight=per_channel))
    for name in float_modules:
        qm.set_module_name(name, None)
    return qm


def _is_qparam(key: str) -> bool:
    return key.endswith((".scale", ".zero_point")) or "_input_scale_" in key or "_input_zero_point_" in key


def _prepare(core: nn.Module, observer: str, float_modules: Sequence[str], example: torch.Tensor):
    *_, prepare_fx, _ = _fx()
    torch.backends.quantized.engine = "x86"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return prepare_fx(core.eval(), _mapping(observer, float_modules), example_inputs=(example,))


def _convert(prepared) -> nn.Module:
    *_, convert_fx = _fx()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert_fx(prepared)


@torch.inference_mode()
def calibrate(core: nn.Module, inputs: Iterable[torch.Tensor], float_modules: Sequence[str] = ()) -> dict[str, float]:
    """Activation ranges of ``core`` (a float module; not modified) over ``inputs`` -> {name: scale or zero point}."""
    import copy

    inputs = list(inputs)
    if not inputs:
        raise ValueError("calibrate: no calibration inputs")
    prepared = _prepare(copy.deepcopy(core), "histogram", float_modules, inputs[0])
    for x in inputs:
        prepared(x)
    q = _convert(prepared)
    return {k: float(v) for k, v in q.state_dict().items() if _is_qparam(k)}


@torch.inference_mode()
def build(core: nn.Module, qparams: dict[str, float], float_modules: Sequence[str], example: torch.Tensor) -> nn.Module:
    """The int8 graph of ``core`` (float, not modified) with the stored activation ranges ``qparams``."""
    import copy

    prepared = _prepare(copy.deepcopy(core), "minmax", float_modules, example)
    prepared(example)  # every observer must have seen data before convert; the ranges are replaced below
    q = _convert(prepared)
    have = {k for k in q.state_dict() if _is_qparam(k)}
    if have != set(qparams):
        from vslam.errors import ConfigError

        raise ConfigError(f"int8 ranges do not fit this network (missing {sorted(have - set(qparams))[:3]}, "
                          f"unknown {sorted(set(qparams) - have)[:3]}): recalibrate")
    for key, val in qparams.items():
        owner_name, _, attr = key.rpartition(".")
        if owner_name:  # a quantised module's output scale / zero point (plain attributes)
            mod = q.get_submodule(owner_name)
            setattr(mod, attr, int(val) if attr == "zero_point" else float(val))
        else:  # an input quantiser's buffer of the graph module
            buf = getattr(q, key)
            buf.copy_(torch.tensor(val, dtype=buf.dtype))
    return q.eval()


def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def qparams_path(weights: str | Path) -> Path:
    p = Path(weights)
    return p.with_name(p.name + QPARAM_SUFFIX)


def save_qparams(weights: str | Path, qparams: dict[str, float], meta: dict) -> Path:
    """Write ``<weights>.int8.json``: the ranges, the weights' SHA-256 and how they were calibrated."""
    out = qparams_path(weights)
    doc = {"weights_sha256": file_sha256(weights), "backend": "x86", "meta": meta, "qparams": qparams}
    out.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return out


def load_qparams(weights: str | Path, command: str) -> tuple[dict[str, float], dict]:
    """The stored ranges of ``weights`` -> (qparams, meta); a one-line error when missing or stale."""
    from vslam.errors import ConfigError

    p = qparams_path(weights)
    if not p.exists():
        raise ConfigError(f"{p}: int8 ranges not found (calibrate them with `{command}`)")
    try:
        doc = json.loads(p.read_text())
        qparams, sha = {str(k): float(v) for k, v in doc["qparams"].items()}, str(doc["weights_sha256"])
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ConfigError(f"{p}: not an int8 range file ({type(e).__name__}: {e})") from None
    if sha != file_sha256(weights):
        raise ConfigError(f"{p}: calibrated for other weights than {weights} (recalibrate with `{command}`)")
    return qparams, dict(doc.get("meta") or {})
