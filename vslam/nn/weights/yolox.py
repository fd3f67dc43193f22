"""Megvii's public YOLOX weights (Apache-2.0) from their ONNX export onto ``vslam.nn.detectors.yolox.YOLOX``.

The export has every BatchNorm folded into its convolution (weight W', bias b'). Our network keeps conv + BN so
that it can be fine-tuned; a folded layer loads as conv weight W' and a BN that is the identity plus the bias:
mean 0, variance 1 - eps (so that sqrt(var + eps) = 1), scale 1, shift b'. In eval mode that is W' x + b', the
export's arithmetic; fine-tuning then starts from the source network's function, with BN statistics that batch
statistics replace as they are re-estimated.

Layers are matched by order (the export's Conv nodes in graph order against ``conv_order``), each with a shape
check, so an export of another width, depth or class count is one ConfigError line naming the first layer that
does not fit. The class head keeps the COCO rows of the network's ``classes``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from vslam.errors import ConfigError
from vslam.nn.weights import pretrained_file


def read_onnx_convs(path: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(node name, weight, bias) of every Conv node of the ONNX graph at ``path``, in graph order."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        raise ConfigError("reading the public YOLOX weights needs the onnx package: pip install vslam[train]") from None
    try:
        graph = onnx.load(str(path)).graph
    except Exception as e:
        raise ConfigError(f"{path}: not an ONNX file ({type(e).__name__})") from None
    inits = {t.name: t for t in graph.initializer}
    out = []
    for node in graph.node:
        if node.op_type != "Conv":
            continue
        if len(node.input) < 3 or node.input[1] not in inits or node.input[2] not in inits:
            raise ConfigError(f"{path}: Conv node {node.name!r} has no constant weight and bias (not a BN-folded export)")
        out.append((node.name, numpy_helper.to_array(inits[node.input[1]]), numpy_helper.to_array(inits[node.input[2]])))
    return out


def convert(model: torch.nn.Module, source: str | Path | None = None) -> dict[str, torch.Tensor]:
    """Our state dict for ``model`` (a YOLOX) from the ONNX file ``source`` (default the shared data's
    pretrained/yolox_nano/yolox_nano.onnx). Attention blocks (absent from the source) keep the model's own
    initial values: their gates are zero, so they change nothing."""
    from vslam.nn.detectors.coco import COCO80
    from vslam.nn.detectors.yolox import BaseConv, conv_order

    path = pretrained_file(source, "yolox_nano", "yolox_nano.onnx")
    unknown = [n for n in model.names if n not in COCO80]
    if unknown:
        raise ConfigError(f"YOLOX classes {', '.join(map(repr, unknown))} are not COCO classes; the public weights "
                          f"know COCO's 80 (vslam.nn.detectors.coco)")
    rows = torch.tensor([COCO80.index(n) for n in model.names])
    convs = read_onnx_convs(path)
    targets = conv_order(model)
    if len(convs) != len(targets):
        raise ConfigError(f"{path}: {len(convs)} convolutions, the network has {len(targets)} "
                          f"(depth {model.conf['depth']}, width {model.conf['width']}): another YOLOX size")
    state: dict[str, torch.Tensor] = {}
    for (node, w, b), (name, layer) in zip(convs, targets):
        w, b = torch.from_numpy(w.copy()).float(), torch.from_numpy(b.copy()).float()
        if ".cls_preds." in name:
            if w.shape[0] != len(COCO80):
                raise ConfigError(f"{path}: {node} has {w.shape[0]} class rows, not COCO's 80")
            w, b = w[rows], b[rows]
        conv = layer.conv if isinstance(layer, BaseConv) else layer
        if w.shape != conv.weight.shape:
            raise ConfigError(f"{path}: {node} is {tuple(w.shape)}, our {name} expects {tuple(conv.weight.shape)}")
        if isinstance(layer, BaseConv):
            eps = layer.bn.eps
            state[f"{name}.conv.weight"] = w
            state[f"{name}.bn.weight"] = torch.ones_like(b)
            state[f"{name}.bn.bias"] = b
            state[f"{name}.bn.running_mean"] = torch.zeros_like(b)
            state[f"{name}.bn.running_var"] = torch.full_like(b, 1.0 - eps)
            state[f"{name}.bn.num_batches_tracked"] = torch.tensor(0)
        else:
            state[f"{name}.weight"], state[f"{name}.bias"] = w, b
    own = model.state_dict()
    for k, v in own.items():
        if k.startswith("attention."):
            state[k] = v.detach().clone()
    missing = [k for k in own if k not in state]
    assert not missing, f"conversion left {missing[:3]} unset"  # conv_order covers every layer: a programming error
    return state


LICENCE = "Apache-2.0 (weights: Megvii YOLOX; LICENSE.YOLOX-Apache-2.0 beside the source file)"
SOURCE = "YOLOX-nano ONNX export, hamacom2004jp/iinfer @ c7f9a3c : models/yolox_nano.onnx (Megvii YOLOX, COCO)"
COMMAND = "vslam train convert-yolox"


def convert_to_file(out: str | Path, source: str | Path | None = None, classes: tuple[str, ...] | None = None,
                    attention: str = "none", half: bool = False) -> tuple[Path, dict]:
    """Convert the public YOLOX-nano once and save it in our checkpoint format (``save_model``) at ``out``:
    ``classes`` (default the SLAM classes) sliced from COCO's 80, ``attention`` blocks zero-gated, float32 weights
    (``half``: float16, half of 3.7 MB, but probabilities move by up to ~1e-2 on real frames). -> (path, meta);
    meta names the source (and its SHA-256), licence and command, and ``max_abs_diff_stored``: the largest change
    of an output probability on a fixed random input from the stored precision (0 in float32)."""
    import hashlib

    from vslam.nn.checkpoint import load_model, save_model
    from vslam.nn.detectors.coco import SLAM_CLASSES
    from vslam.nn.registry import DETECTORS

    path = pretrained_file(source, "yolox_nano", "yolox_nano.onnx")
    names = list(classes or SLAM_CLASSES)
    model = DETECTORS.pretrained("yolox-nano", {"classes": names, "attention": attention}, source=str(path))
    meta = {"source": SOURCE, "source_sha256": hashlib.sha256(path.read_bytes()).hexdigest(), "licence": LICENCE,
            "command": f"{COMMAND} --attention {attention}" + (" --float16" if half else "")
                       + (f" --classes {','.join(names)}" if classes else ""),
            "classes": names, "dtype": "float16" if half else "float32"}
    out = save_model(model, out, "yolox-nano", meta, half=half)
    # what the stored precision changes, on a fixed random input (recorded; the tests bound it on real frames)
    x = torch.from_numpy(np.random.default_rng(0).uniform(0, 255, (1, 3, 416, 416)).astype(np.float32))
    loaded, _ = load_model(out, DETECTORS)
    with torch.no_grad():
        diff = (loaded({"image": x})["pred"][..., 4:] - model({"image": x})["pred"][..., 4:]).abs().max()
    meta["max_abs_diff_stored"] = float(diff)
    save_model(loaded if half else model, out, "yolox-nano", meta, half=half)
    return out, meta
