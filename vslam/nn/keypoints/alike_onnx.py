"""ALIKE's dense part (the encoder's four projected levels and the score map) run by onnxruntime instead of torch.

Why: on a 2-core machine shared with other jobs, torch's two intra-op threads wait on each other at every layer
(docs/features.md, 'Speed'); onnxruntime's thread pool loses far less there. On one thread both run at about the
same speed. Detection and the sparse descriptors stay in torch (``ALIKE.candidates``, ``refine``, ``describe``):
they read the levels, which come back as torch tensors viewing onnxruntime's arrays.

The graph is exported from the loaded (folded) network in memory when the runtime is built, so it always holds the
weights torch would run; nothing is written to disk. onnxruntime is optional (extras ``dev``, ``teacher``):
``OnnxMaps`` raises one ConfigError line where it is not installed.
"""

from __future__ import annotations

import io
import warnings

import torch
import torch.nn.functional as F
from torch import nn

from vslam.nn.keypoints.alike import ALIKE, PAD


class _Dense(nn.Module):
    """(1,3,Hp,Wp) padded image -> the four levels and the (1,1,Hp,Wp) score map (not cropped: the export keeps
    H and W symbolic)."""

    def __init__(self, model: ALIKE):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        levels = self.model.levels(x)
        return (*levels, self.model.score_map(levels, (x.shape[-2], x.shape[-1])))


def export_onnx(model: ALIKE) -> bytes:
    """The ONNX graph (opset 17, input ``image`` (1,3,H,W) with H, W multiples of 32 and symbolic) of ``model``'s
    levels and score map."""
    dense = _Dense(model).eval()
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter is flagged as deprecated; it is what works here
        torch.onnx.export(dense, (torch.zeros(1, 3, 2 * PAD, 2 * PAD),), buf, input_names=["image"],
                          output_names=["l1", "l2", "l3", "l4", "score"], opset_version=17, dynamo=False,
                          dynamic_axes={"image": {2: "h", 3: "w"}})
    return buf.getvalue()


class OnnxMaps:
    """``maps(x, hw)`` -> (levels, (h,w) score map) as ``ALIKE.levels`` + ``score_map`` give them, by onnxruntime.

    x: (1,3,h,w) float32 image in [0,1] (any memory layout); hw: (h, w). One session per thread count, built at the
    first call with torch's current intra-op thread count (the run's ``runtime.torch_threads``)."""

    def __init__(self, model: ALIKE):
        from vslam.errors import ConfigError

        try:
            import onnxruntime  # noqa: F401
        except ImportError:
            raise ConfigError("slam.features.runtime=onnxruntime needs onnxruntime (pip install onnxruntime; "
                              "it is in the extras dev and teacher)") from None
        self.graph = export_onnx(model)
        self._sessions: dict[int, object] = {}

    def session(self, threads: int):
        import onnxruntime as ort

        if threads not in self._sessions:
            so = ort.SessionOptions()
            so.intra_op_num_threads, so.inter_op_num_threads = threads, 1
            so.log_severity_level = 3
            # waiting threads sleep, as torch's do (vslam/__init__.py: OMP_WAIT_POLICY)
            so.add_session_config_entry("session.intra_op.allow_spinning", "0")
            self._sessions[threads] = ort.InferenceSession(self.graph, so, providers=["CPUExecutionProvider"])
        return self._sessions[threads]

    def __call__(self, x: torch.Tensor, hw: tuple[int, int]) -> tuple[list[torch.Tensor], torch.Tensor]:
        h, w = hw
        xp = F.pad(x, (0, -w % PAD, 0, -h % PAD)).contiguous().numpy()
        *levels, score = self.session(torch.get_num_threads()).run(None, {"image": xp})
        return [torch.from_numpy(v) for v in levels], torch.from_numpy(score)[0, 0, :h, :w]
