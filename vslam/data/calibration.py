"""One check of the calibration every reader builds (camera file, ORB-SLAM3 settings, KITTI calib.txt, EuRoC
sensor.yaml, TUM defaults and calibration.yaml, bag camera_info): numbers a camera cannot have are refused when
the sequence opens, with the file, the field (as the file spells it), its line where known and the range expected,
instead of a run that ends in a linear-algebra error or in "no frame tracked".

Checked (``check_camera``, ``check_calibration``):

- fx, fy finite and > 0 pixels; fx/fy within ``FOCAL_RATIO`` (0.2..5: square-ish pixels; a ratio beyond is a
  typo, a swapped field or a value in other units);
- cx in [0, width], cy in [0, height] (once the image size is known; before, cx, cy >= 0);
- width, height positive integers (0: not known yet);
- distortion coefficients finite, radial ones (radtan k1 k2, equidistant k1..k4) within +-``RADIAL_MAX``,
  radtan k3 within +-``RADIAL_K3_MAX``, tangential p1 p2 within +-``TANGENTIAL_MAX`` (real radtan and fisheye
  calibrations are far inside: EuRoC's k1 is -0.28, TUM freiburg1's k3 1.16, TUM-VI's fisheye k1 0.003);
- a stereo pair's baseline finite and > 0 metres, its extrinsics finite; a depth scale finite and > 0.

``check_image_size`` compares an image's decoded size with the size a file declares; ``image_file_size`` reads
it (a PNG's header only, other formats decoded).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import numpy as np

from vslam.data.types import Calibration, PinholeCamera
from vslam.errors import DatasetError

FOCAL_RATIO = (0.2, 5.0)  # fx / fy
RADIAL_MAX = 10.0  # |k1|, |k2| (radtan), |k1..k4| (equidistant)
RADIAL_K3_MAX = 100.0  # |k3| of radtan: it multiplies r^6, small inside the image
TANGENTIAL_MAX = 1.0  # |p1|, |p2| (real lenses: 1e-3)

# field -> (its name in the file, its line there); a field not given is named as here, without a line
Where = Mapping[str, "tuple[str, int | None]"]

_COEFFS = {"radtan": ("k1", "k2", "p1", "p2", "k3"), "equidistant": ("k1", "k2", "k3", "k4"), "none": ()}


def _fmt(v: float) -> str:
    return f"{v:g}"


def check_camera(cam: PinholeCamera, path: str | Path, where: Where | None = None) -> PinholeCamera:
    """``cam`` itself, or DatasetError(path) naming the first field out of range (see the module doc)."""
    where = where or {}

    def name(key: str) -> tuple[str, int | None]:
        if key in where:
            return where[key]
        if key in _COEFFS["radtan"] + _COEFFS["equidistant"] and "distortion" in where:
            base, line = where["distortion"]
            return f"{base} {key}", line
        return (f"distortion {key}" if key in _COEFFS["radtan"] + _COEFFS["equidistant"] else key), None

    def fail(key: str, value: float, why: str) -> None:
        field, line = name(key)
        raise DatasetError(path, f"{field} = {_fmt(value)}: {why}", line)

    for key in ("width", "height"):
        v = getattr(cam, key)
        if not isinstance(v, (int, np.integer)) or v < 0:
            fail(key, v, "the image size must be a positive integer (pixels)")
    for key in ("fx", "fy"):
        v = float(getattr(cam, key))
        if not (math.isfinite(v) and v > 0):
            fail(key, v, "focal lengths must be finite and > 0 pixels")
    ratio = cam.fx / cam.fy
    if not FOCAL_RATIO[0] <= ratio <= FOCAL_RATIO[1]:
        (nx, _), (ny, line) = name("fx"), name("fy")
        raise DatasetError(path, f"{nx} / {ny} = {_fmt(cam.fx)} / {_fmt(cam.fy)} = {ratio:.3g}: the focal lengths' "
                                 f"ratio must be within {FOCAL_RATIO[0]:g}..{FOCAL_RATIO[1]:g} (near-square pixels)",
                           line)
    for key, size, side in (("cx", cam.width, "width"), ("cy", cam.height, "height")):
        v = float(getattr(cam, key))
        if not math.isfinite(v):
            fail(key, v, "the principal point must be finite")
        if size and not 0 <= v <= size:
            fail(key, v, f"the principal point must lie inside the image: 0..{size} (the image {side}, "
                         f"{cam.width}x{cam.height})")
        if not size and v < 0:
            fail(key, v, "the principal point must lie inside the image (>= 0 pixels)")
    names = _COEFFS.get(cam.distortion_model, ())
    for k, v in enumerate(cam.distortion):
        coef = names[k] if k < len(names) else f"coefficient {k + 1}"
        v = float(v)
        if not math.isfinite(v):
            fail(coef, v, "distortion coefficients must be finite")
        if coef.startswith("p"):
            bound, what = TANGENTIAL_MAX, "tangential"
        elif cam.distortion_model == "radtan" and coef == "k3":
            bound, what = RADIAL_K3_MAX, "radial (r^6)"
        else:
            bound, what = RADIAL_MAX, "radial"
        if abs(v) >= bound:
            fail(coef, v, f"{what} distortion coefficients of a real lens lie within -{bound:g}..{bound:g} "
                          f"({cam.distortion_model} model)")
    return cam


def check_calibration(cal: Calibration, path: str | Path, where0: Where | None = None, path1: str | Path | None = None,
                      where1: Where | None = None, baseline: tuple[str, int | None] = ("baseline", None)) -> Calibration:
    """``cal`` itself, or DatasetError naming the first field out of range: cam0 (named in ``path``/``where0``),
    cam1 (``path1``/``where1``, default cam0's), the stereo baseline (``baseline``: its name and line in
    ``path1`` or ``path``) and the depth scale."""
    check_camera(cal.cam0, path, where0)
    if cal.cam1 is not None:
        check_camera(cal.cam1, path1 or path, where1 if where1 is not None else where0)
    if cal.T_body_cam1 is not None:
        field, line = baseline
        if not (np.all(np.isfinite(cal.T_body_cam0)) and np.all(np.isfinite(cal.T_body_cam1))):
            raise DatasetError(path1 or path, f"{field}: the stereo extrinsics must be finite", line)
        b = cal.baseline
        if b is None or not (math.isfinite(b) and b > 0):
            raise DatasetError(path1 or path, f"{field}: stereo baseline = {_fmt(b or 0.0)} m: the two cameras' "
                                              "centres must be apart (a finite baseline > 0 metres)", line)
    if cal.depth_scale is not None and not (math.isfinite(cal.depth_scale) and cal.depth_scale > 0):
        raise DatasetError(path, f"depth_scale = {_fmt(cal.depth_scale)}: raw depth units per metre must be finite "
                                 "and > 0")
    return cal


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk (24 bytes read, nothing decoded), None if not a PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def image_file_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image file: a PNG's header, else the decoded image; None when it does not decode
    (the reader skips that frame later, with its warning)."""
    size = png_size(path)
    if size is not None:
        return size
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return None if img is None else (int(img.shape[1]), int(img.shape[0]))


def check_image_size(cam: PinholeCamera, size: tuple[int, int] | None, image: str | Path, declared: str) -> None:
    """DatasetError(image) when the image's (width, height) ``size`` is not the camera's; ``declared`` says
    where the camera's size comes from ("cam0/sensor.yaml resolution", ...). None (unknown) passes."""
    if size is None or size == (cam.width, cam.height):
        return
    raise DatasetError(image, f"image is {size[0]}x{size[1]}, but {declared} says {cam.width}x{cam.height}: "
                              "the calibration is of another image size")
