"""FastestDet (github.com/dog-qiuqiu/FastestDet, BSD-3), the public 0.24 M-parameter COCO-80 detector of the
detector-data comparison, run through onnxruntime: a reference to beat and a teacher (pseudo-boxes, distillation),
never the shipped model.

onnxruntime is the optional extra ``vslam[teacher]``, imported only when a teacher is built. The model file lives
in the data folder (``$VSLAM_DATA/teachers/fastestdet/FastestDet.onnx``), not in the package.

Decoding follows the reference implementation's ``detection()``: input 1x3x352x352 BGR / 255 after a plain
resize (no letterbox); output 1x85x22x22, per cell objectness, x/y offsets (tanh, in cells), w/h (sigmoid, in
image fractions) and 80 class scores; one box per cell of its best class, score = obj^0.6 * cls^0.4; then
class-agnostic NMS at IoU 0.45.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vslam.dynamic.detector import Detections
from vslam.errors import ConfigError
from vslam.nn.detectors.coco import COCO80

# the score threshold of the detector-data comparison of FastestDet (docs/detector-data.md, 'Measurements behind
# settings in the code')
TEACHER_THRESHOLD = 0.5


def default_teacher_path() -> Path:
    from vslam.paths import data_root

    return data_root() / "teachers" / "fastestdet" / "FastestDet.onnx"


class FastestDet:
    """``detect(image)``: BGR or grey uint8 image -> Detections (COCO-80 names) in that image's pixels, the same
    interface as ``vslam.dynamic.detector.Detector``."""

    def __init__(self, path: str | Path = "", conf: float = 0.001, iou: float = 0.45, threads: int = 2,
                 size: int = 352):
        try:
            import onnxruntime as ort
        except ImportError:
            raise ConfigError("the FastestDet teacher runs on onnxruntime: pip install 'vslam[teacher]'") from None
        path = Path(path) if path else default_teacher_path()
        if not path.is_file():
            raise ConfigError(f"{path}: FastestDet ONNX file not found (teachers/fastestdet under $VSLAM_DATA)")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        self.input = self.session.get_inputs()[0].name
        self.names, self.conf, self.iou, self.size = list(COCO80), conf, iou, size

    def raw(self, image: np.ndarray) -> np.ndarray:
        """(85, G, G) float32: the network's output for ``image`` (BGR or grey uint8)."""
        bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        x = cv2.resize(bgr, (self.size, self.size), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        return self.session.run(None, {self.input: x.transpose(2, 0, 1)[None]})[0][0]

    def detect(self, image: np.ndarray) -> Detections:
        boxes, scores, cls = decode(self.raw(image), image.shape[1], image.shape[0], self.conf)
        keep = _nms(boxes, scores, cls, self.iou)
        boxes, scores, cls = boxes[keep], scores[keep], cls[keep]
        return Detections(boxes, scores, cls, np.array([self.names[i] for i in cls], dtype=object))


def decode(out: np.ndarray, width: int, height: int, conf: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FastestDet's (85, G, G) output -> boxes (K,4) x1,y1,x2,y2 pixels of a ``width`` x ``height`` image, scores
    (K,) and COCO-80 classes (K,) of the cells scoring above ``conf`` (module docstring)."""
    _, gh, gw = out.shape
    obj, reg, cls_p = out[0], out[1:5], out[5:]
    cls = cls_p.argmax(0)
    score = obj.clip(0, None) ** 0.6 * np.take_along_axis(cls_p, cls[None], 0)[0].clip(0, None) ** 0.4
    ys, xs = np.nonzero(score > conf)
    cx = (xs + np.tanh(reg[0, ys, xs])) / gw
    cy = (ys + np.tanh(reg[1, ys, xs])) / gh
    bw, bh = 1 / (1 + np.exp(-reg[2, ys, xs])), 1 / (1 + np.exp(-reg[3, ys, xs]))
    boxes = np.stack([(cx - bw / 2) * width, (cy - bh / 2) * height, (cx + bw / 2) * width, (cy + bh / 2) * height], 1)
    return boxes.astype(np.float64).reshape(-1, 4), score[ys, xs].astype(np.float64), cls[ys, xs].astype(np.int64)


def _nms(boxes: np.ndarray, scores: np.ndarray, cls: np.ndarray, iou: float) -> np.ndarray:
    """Class-agnostic, as the reference's ONNX runtime sample (``nms(dets, thresh=0.45)``)."""
    import torch

    from vslam.nn.ops import nms

    if not len(boxes):
        return np.zeros(0, np.int64)
    return nms(torch.from_numpy(boxes), torch.from_numpy(scores), iou).numpy()
