"""BlazePose-lite (MediaPipe, Apache-2.0) as a box-prompted person-mask teacher: a training-time tool that gives
pseudo-masks for person boxes in real photos without masks, to train our own mask head. Never run by SLAM.

The network is ``pose_landmark_lite.tflite`` of the npm package @mediapipe/pose (``$VSLAM_DATA/pretrained/
mask_teachers/blazepose_lite.tflite``), run with the ``ai-edge-litert`` package (the optional extra
``vslam[train]``, imported only when a teacher is built). Its conventions (pretrained/README.md of the data
folder): input 1x256x256x3 RGB in [0, 1], a square crop around one person (``margin`` times the box's longer side,
centred on the box, outside the image black); output ``Identity_2`` is a 1x256x256x1 segmentation logit map of the
crop. A mask is that map warped back into the image (bilinear on the logits), cut at probability ``threshold`` and
clipped to the box.

Pseudo-masks are cached on disk (``cached_masks``): one ``.npz`` per image and box set, keyed by the image's
path, its boxes and the teacher's settings, so a second training run reads them instead of rerunning the teacher.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import cv2
import numpy as np

from vslam.errors import ConfigError

log = logging.getLogger(__name__)

INPUT_SIDE = 256
OUTPUT_NAME = "Identity_2"  # the segmentation logits (the other outputs are landmarks and scores)


def default_teacher_path() -> Path:
    from vslam.paths import data_root

    return data_root() / "pretrained" / "mask_teachers" / "blazepose_lite.tflite"


def crop_transform(box: np.ndarray, margin: float = 1.2, side: int = INPUT_SIDE) -> np.ndarray:
    """(2,3) affine from image pixels to the teacher's ``side`` x ``side`` crop: the square of ``margin`` times the
    box's longer side, centred on the box (x1, y1, x2, y2 pixels, x2/y2 exclusive). Pixel centres map to pixel
    centres (OpenCV's convention: pixel i covers [i - 0.5, i + 0.5])."""
    x1, y1, x2, y2 = (float(v) for v in box)
    s = max(x2 - x1, y2 - y1, 1.0) * margin  # crop side, image pixels
    k = side / s
    # the crop's left edge x0 = cx - s/2 (a pixel-edge coordinate) -> crop edge 0: u + 0.5 = k (x + 0.5 - x0)
    x0, y0 = (x1 + x2) / 2 - s / 2, (y1 + y2) / 2 - s / 2
    return np.array([[k, 0.0, k * (0.5 - x0) - 0.5], [0.0, k, k * (0.5 - y0) - 0.5]], np.float64)


def crop_input(image_bgr: np.ndarray, box: np.ndarray, margin: float = 1.2, side: int = INPUT_SIDE) -> np.ndarray:
    """The teacher's input for ``box``: (side, side, 3) float32 RGB in [0, 1], black outside the image."""
    A = crop_transform(box, margin, side)
    crop = cv2.warpAffine(image_bgr, A, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(0, 0, 0))
    return cv2.cvtColor(crop, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def paste_logits(logits: np.ndarray, box: np.ndarray, shape: tuple[int, int], margin: float = 1.2,
                 threshold: float = 0.5) -> np.ndarray:
    """The crop's (side, side) logit map back in the image: (H, W) bool, True where the bilinearly warped logit is
    above logit(``threshold``), inside ``box`` only (rounded to the pixel grid, clipped to the image)."""
    H, W = shape
    side = logits.shape[0]
    out = np.zeros((H, W), bool)
    bx1, by1, bx2, by2 = np.round(np.asarray(box, np.float64)).astype(int)
    bx1, by1, bx2, by2 = max(bx1, 0), max(by1, 0), min(bx2, W), min(by2, H)
    if bx2 <= bx1 or by2 <= by1:
        return out
    A = crop_transform(box, margin, side)
    A[:, 2] += A[:, :2] @ [bx1, by1]  # the window's pixel (0, 0) is the image's (bx1, by1)
    win = cv2.warpAffine(logits.astype(np.float32), A, (bx2 - bx1, by2 - by1),
                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=-1e4)
    cut = float(np.log(threshold / (1.0 - threshold)))
    out[by1:by2, bx1:bx2] = win > cut
    return out


class BlazePoseTeacher:
    """``masks(image, boxes)``: BGR (or grey) uint8 image and (K, 4) person boxes -> (K, H, W) bool masks.
    ``margin``: crop side over the box's longer side; ``threshold``: mask probability cut; ``threads``: the
    interpreter's CPU threads."""

    def __init__(self, path: str | Path = "", threads: int = 2, margin: float = 1.2, threshold: float = 0.5):
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError:
            raise ConfigError("the BlazePose mask teacher runs on ai-edge-litert: pip install 'vslam[train]'") from None
        self.path = Path(path) if path else default_teacher_path()
        if not self.path.is_file():
            raise ConfigError(f"{self.path}: BlazePose-lite TFLite file not found (pretrained/mask_teachers under "
                              f"$VSLAM_DATA)")
        if not 1.0 <= margin <= 3.0 or not 0.0 < threshold < 1.0:
            raise ConfigError(f"mask teacher: margin must be in [1, 3] and threshold in (0, 1), got {margin}, {threshold}")
        self.margin, self.threshold = float(margin), float(threshold)
        self.interp = Interpreter(model_path=str(self.path), num_threads=threads)
        self.interp.allocate_tensors()
        inp = self.interp.get_input_details()[0]
        if tuple(inp["shape"]) != (1, INPUT_SIDE, INPUT_SIDE, 3):
            raise ConfigError(f"{self.path}: input {tuple(inp['shape'])}, BlazePose-lite takes (1, 256, 256, 3)")
        self._in = inp["index"]
        outs = self.interp.get_output_details()
        seg = [o for o in outs if o["name"] == OUTPUT_NAME] or [o for o in outs if tuple(o["shape"]) == (1, INPUT_SIDE, INPUT_SIDE, 1)]
        if not seg:
            raise ConfigError(f"{self.path}: no {OUTPUT_NAME} (1x256x256x1) output; not BlazePose-lite")
        self._out = seg[0]["index"]

    def logits(self, crop: np.ndarray) -> np.ndarray:
        """(256, 256, 3) float32 RGB [0, 1] crop -> (256, 256) float32 segmentation logits."""
        self.interp.set_tensor(self._in, np.ascontiguousarray(crop[None], np.float32))
        self.interp.invoke()
        return self.interp.get_tensor(self._out)[0, ..., 0].astype(np.float32)

    def mask(self, image: np.ndarray, box: np.ndarray) -> np.ndarray:
        """(H, W) bool mask of the person in ``box`` (x1, y1, x2, y2 pixels)."""
        bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        lg = self.logits(crop_input(bgr, box, self.margin))
        return paste_logits(lg, box, bgr.shape[:2], self.margin, self.threshold)

    def masks(self, image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        out = np.zeros((len(boxes), *image.shape[:2]), bool)
        for i, b in enumerate(boxes):
            out[i] = self.mask(image, b)
        return out

    def key(self) -> str:
        """What the cached masks depend on besides the image and boxes."""
        return f"blazepose-lite:{self.path.stat().st_size}:{self.margin:g}:{self.threshold:g}"


def cached_masks(teacher: BlazePoseTeacher, image: np.ndarray, boxes: np.ndarray, name: str,
                 cache: str | Path) -> np.ndarray:
    """``teacher.masks(image, boxes)``, read from / written to ``cache`` (a folder; masks stored packed, keyed by
    ``name`` (the image's path or another unique id), the boxes and ``teacher.key()``)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    h = hashlib.sha1(f"{name}|{teacher.key()}|{image.shape}".encode() + boxes.round(2).tobytes()).hexdigest()[:20]
    path = Path(cache) / f"{h}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                return np.unpackbits(z["bits"], count=int(np.prod(z["shape"]))).reshape(z["shape"]).astype(bool)
        except (OSError, ValueError, KeyError):
            log.warning("%s: unreadable cached pseudo-masks; recomputed", path)
    masks = teacher.masks(image, boxes)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, bits=np.packbits(masks.reshape(-1)), shape=np.array(masks.shape))
    tmp.replace(path)
    return masks
