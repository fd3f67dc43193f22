"""Camera files for user data: our ``camera.yaml`` or an ORB-SLAM3 settings file.

Our format (every key but fx fy cx cy optional; paths relative to the file)::

    fx: 535.4            # pixels
    fy: 539.2
    cx: 320.1
    cy: 247.6
    width: 640           # default: the first image's size
    height: 480
    distortion_model: radtan     # none | radtan (k1 k2 p1 p2 [k3]) | equidistant (k1 k2 k3 k4)
    distortion: [0.0, 0.0, 0.0, 0.0]
    images: rgb          # image folder, when --data names the folder holding this file
    depth: depth         # 16-bit depth images (same names, or numeric time stems matched in time)
    depth_scale: 5000    # raw depth units per metre
    right: right         # right stereo images (same names as the left ones)
    baseline: 0.11       # metres; the right camera sits at +x of the left one (rectified pair)
    fps: 30              # frame rate, when file names are not timestamps and no times file is given
    T_body_cam: [16 numbers, row-major]   # camera in the IMU frame (bags with an IMU topic)
    imu: {gyro_noise_density: ..., gyro_random_walk: ..., accel_noise_density: ..., accel_random_walk: ..., rate_hz: ...}

ORB-SLAM3 settings (``%YAML:1.0`` header, OpenCV FileStorage): ``Camera.fx`` or ``Camera1.fx`` ...,
``Camera.k1 k2 p1 p2 [k3]`` (``Camera.type: KannalaBrandt8``: k1..k4; ``Rectified``: none), ``Camera.width/height``,
``Camera.fps``, ``DepthMapFactor`` (= depth_scale), ``Stereo.b`` or ``Camera.bf`` (baseline x fx),
``Stereo.T_c1_c2``, ``IMU.T_b_c1`` / ``Tbc`` and ``IMU.NoiseGyro/NoiseAcc/GyroWalk/AccWalk/Frequency``.
A stereo file of the v1.0 format may give the right camera its own intrinsics and distortion (``Camera2.fx``
..., ``Camera2.k1`` ...): the pair is then unrectified, as EuRoC's, with ``Stereo.T_c1_c2`` (the right camera
in the left camera's frame: it maps points from camera 2 to camera 1) as ``T_cam0_cam1``.
Their depth and right folders are ``depth/`` and ``right/`` beside the image folder.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vslam.data.calibration import Where, check_calibration, check_camera
from vslam.data.euroc import parse_distortion_model
from vslam.data.textio import read_yaml_mapping
from vslam.data.types import Calibration, ImuNoise, PinholeCamera
from vslam.errors import DatasetError

CAMERA_FILE_NAME = "camera.yaml"
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "distortion_model", "distortion", "images", "depth",
               "depth_scale", "right", "baseline", "fps", "T_body_cam", "imu")
_COUNTS = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}


@dataclass(frozen=True, eq=False)
class CameraFile:
    """What a camera file says. ``camera.width``/``height`` are 0 when the file leaves them to the images."""

    path: Path
    camera: PinholeCamera
    images: Path | None = None
    depth: Path | None = None
    depth_scale: float | None = None
    right: Path | None = None
    T_cam0_cam1: np.ndarray | None = None  # (4,4), right camera in the left camera's frame
    fps: float | None = None
    T_body_cam: np.ndarray | None = None  # (4,4), camera in the IMU (body) frame
    imu: ImuNoise | None = None
    camera1: PinholeCamera | None = None  # the right camera when the file gives its own intrinsics (Camera2.*)
    # where each field is in the file (name as spelt there, line): what ``check_calibration`` names
    where: Where = field(default_factory=dict)
    where1: Where | None = None  # the right camera's (Camera2.*)

    def calibration(self, width: int, height: int, sensor: str, image: str | Path | None = None) -> Calibration:
        """The Calibration of a ``sensor`` run; a size the file left open becomes the images' ``width``x``height``
        (of ``image``: the first image or the video, named when its size is not the file's). Checked by
        ``vslam.data.calibration.check_calibration`` (principal point inside the image, baseline > 0, ...)."""
        cam = self.camera
        if cam.width == 0 or cam.height == 0:
            cam = dataclasses.replace(cam, width=width, height=height)
        elif (cam.width, cam.height) != (width, height):
            if image is not None:
                raise DatasetError(image, f"camera is {cam.width}x{cam.height} but the images are {width}x{height}; "
                                          f"fix width/height in {self.path} (or leave them out to take the images' "
                                          "size)")
            raise DatasetError(self.path, f"camera is {cam.width}x{cam.height} but the images are {width}x{height}; "
                                          "fix width/height (or leave them out to take the images' size)")
        cam1 = cam  # a rectified pair: the right camera is the left one shifted along x
        if self.camera1 is not None:
            cam1 = dataclasses.replace(self.camera1, width=cam.width, height=cam.height)
        T_bc0 = self.T_body_cam if self.T_body_cam is not None else np.eye(4)
        stereo = sensor == "stereo" and self.T_cam0_cam1 is not None
        cal = Calibration(cam0=cam, cam1=cam1 if stereo else None, T_body_cam0=T_bc0,
                          T_body_cam1=T_bc0 @ self.T_cam0_cam1 if stereo else None,
                          imu=self.imu, depth_scale=self.depth_scale if sensor == "rgbd" else None)
        return check_calibration(cal, self.path, self.where, where1=self.where1,
                                 baseline=self.where.get("baseline", ("baseline", None)))


def read_camera_file(path: Path) -> CameraFile:
    """Either format, told apart by the ``%YAML:1.0`` header of OpenCV FileStorage files."""
    if not path.is_file():
        raise DatasetError(path, "missing camera file (YAML with fx, fy, cx, cy; see docs/inputs.md); "
                                 "give one with --camera or dataset.camera")
    try:
        head = path.read_text().lstrip()[:9]
    except UnicodeDecodeError:
        raise DatasetError(path, "camera file is not a text file") from None
    return _read_opencv(path) if head.startswith("%YAML") else _read_ours(path)


def _positive(path: Path, key: str, v: Any, line: int | None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise DatasetError(path, f"{key!r} must be a positive number, got {v!r}", line)
    return float(v)


def _finite(path: Path, key: str, v: Any, line: int | None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise DatasetError(path, f"{key!r} must be a finite number, got {v!r}", line)
    return float(v)


def _numbers(path: Path, key: str, v: Any, line: int | None) -> tuple[float, ...]:
    if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v) \
            or not all(math.isfinite(x) for x in v):
        raise DatasetError(path, f"{key!r} must be a list of finite numbers, got {v!r}", line)
    return tuple(float(x) for x in v)


def _check_distortion(path: Path, model: str, dist: tuple[float, ...], line: int | None) -> tuple[float, ...]:
    if model == "none":
        if any(dist):
            raise DatasetError(path, "distortion coefficients given with distortion_model 'none'", line)
        return ()
    if len(dist) not in _COUNTS[model]:
        want = " or ".join(map(str, _COUNTS[model]))
        raise DatasetError(path, f"distortion_model {model!r} takes {want} coefficients, found {len(dist)}", line)
    return dist


def _rigid(path: Path, key: str, values: tuple[float, ...], line: int | None) -> np.ndarray:
    if len(values) not in (12, 16):
        raise DatasetError(path, f"{key!r} must hold 16 numbers (a 4x4 row-major matrix), found {len(values)}", line)
    T = np.eye(4)
    T[: len(values) // 4] = np.reshape(values, (-1, 4))
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise DatasetError(path, f"{key!r}: the 3x3 part is not a rotation", line)
    return T


def _baseline_T(b: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = b  # rectified pair: the right camera centre at +x in the left camera frame
    return T


def _read_ours(path: Path) -> CameraFile:
    data, lines = read_yaml_mapping(path)
    for key in data:
        if key not in CAMERA_KEYS:
            raise DatasetError(path, f"unknown key {key!r}; allowed: {', '.join(CAMERA_KEYS)}", lines.get(str(key)))
    for key in ("fx", "fy", "cx", "cy"):
        if key not in data:
            raise DatasetError(path, f"missing key {key!r} (camera intrinsics in pixels: fx, fy, cx, cy)")
    # fx, fy > 0 here; the principal point's range, the focal ratio and the distortion: check_camera below
    k = {key: (_positive if key in ("fx", "fy") else _finite)(path, key, data[key], lines.get(key))
         for key in ("fx", "fy", "cx", "cy")}
    size = {}
    for key in ("width", "height"):
        v = data.get(key, 0)
        if key in data and (_positive(path, key, v, lines.get(key)) != int(v)):
            raise DatasetError(path, f"{key!r} must be an integer, got {v!r}", lines.get(key))
        size[key] = int(v)
    model = parse_distortion_model(path, data.get("distortion_model", "none"), lines.get("distortion_model"))
    dist = _numbers(path, "distortion", data.get("distortion", []), lines.get("distortion"))
    dist = _check_distortion(path, model, dist, lines.get("distortion"))
    cam = PinholeCamera(size["width"], size["height"], k["fx"], k["fy"], k["cx"], k["cy"], model, dist)
    where = {key: (key, lines.get(key)) for key in ("fx", "fy", "cx", "cy", "width", "height", "distortion",
                                                     "baseline")}
    check_camera(cam, path, where)
    folder = {}
    for key in ("images", "depth", "right"):
        if key in data:
            if not isinstance(data[key], str) or not data[key]:
                raise DatasetError(path, f"{key!r} must be a folder path, got {data[key]!r}", lines.get(key))
            folder[key] = (path.parent / data[key]).expanduser()
    opt = {key: _positive(path, key, data[key], lines.get(key)) for key in ("depth_scale", "baseline", "fps")
           if key in data}
    T_bc = None
    if "T_body_cam" in data:
        T_bc = _rigid(path, "T_body_cam", _numbers(path, "T_body_cam", data["T_body_cam"], lines.get("T_body_cam")),
                      lines.get("T_body_cam"))
    imu = None
    if "imu" in data:
        imu = _imu_noise(path, data["imu"], lines.get("imu"))
    return CameraFile(path, cam, folder.get("images"), folder.get("depth"), opt.get("depth_scale"), folder.get("right"),
                      _baseline_T(opt["baseline"]) if "baseline" in opt else None, opt.get("fps"), T_bc, imu,
                      where=where)


def _imu_noise(path: Path, v: Any, line: int | None) -> ImuNoise:
    names = [f.name for f in dataclasses.fields(ImuNoise)]
    if not isinstance(v, dict):
        raise DatasetError(path, f"'imu' must be a mapping of {', '.join(names)}", line)
    for key in v:
        if key not in names:
            raise DatasetError(path, f"unknown key 'imu.{key}'; allowed: {', '.join(names)}", line)
    return ImuNoise(**{key: _positive(path, f"imu.{key}", val, line) for key, val in v.items()})


# ----------------------------------------------------------------------------- ORB-SLAM3 settings


class _Settings:
    """Read access to an OpenCV FileStorage file whose errors name the key and its line."""

    def __init__(self, path: Path):
        self.path = path
        self.text = path.read_text().splitlines()
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as e:  # a parse error (the SystemError wraps OpenCV's cv2.error)
            cause = e if isinstance(e, cv2.error) else (e.__cause__ or e.__context__ or e)
            m = re.search(r"\((\d+)\): ([^'\n]*)", str(cause))  # "... in function '<path>(3): Incorrect indentation'"
            why, line = (f" ({m.group(2).strip()})", int(m.group(1))) if m else ("", None)
            raise DatasetError(path, f"not a readable OpenCV FileStorage YAML (ORB-SLAM3 settings) file{why}",
                               line) from None
        if not fs.isOpened():
            raise DatasetError(path, "not a readable OpenCV FileStorage YAML (ORB-SLAM3 settings) file")
        self.fs = fs

    def line(self, key: str) -> int | None:
        pat = re.compile(rf"^\s*{re.escape(key)}\s*:")
        return next((i for i, ln in enumerate(self.text, 1) if pat.match(ln)), None)

    def has(self, key: str) -> bool:
        return not self.fs.getNode(key).empty()

    def number(self, key: str) -> float:
        node = self.fs.getNode(key)
        if not node.isReal() and not node.isInt():
            raise DatasetError(self.path, f"{key!r} must be a number", self.line(key))
        v = float(node.real())
        if not math.isfinite(v):
            raise DatasetError(self.path, f"{key!r} must be finite, got {v!r}", self.line(key))
        return v

    def matrix(self, key: str) -> tuple[float, ...]:
        m = self.fs.getNode(key).mat()
        if m is None:
            raise DatasetError(self.path, f"{key!r} must be an !!opencv-matrix", self.line(key))
        return tuple(float(x) for x in np.asarray(m, np.float64).ravel())


def _where(s: _Settings, pre: str) -> dict[str, tuple[str, int | None]]:
    """Names and lines of the fields under ``pre`` (``Camera.width``/``height`` whatever ``pre`` is)."""
    where = {key: (pre + key, s.line(pre + key)) for key in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2")}
    where.update({key: (f"Camera.{key}", s.line(f"Camera.{key}")) for key in ("width", "height")})
    return where


def _opencv_camera(s: _Settings, pre: str, cam_type: str, size: dict[str, int]) -> PinholeCamera:
    """The intrinsics and distortion under ``pre`` (``Camera.``, ``Camera1.`` or ``Camera2.``), checked."""
    path = s.path
    k = {}
    for key in ("fx", "fy", "cx", "cy"):
        if not s.has(pre + key):
            raise DatasetError(path, f"missing key {pre + key!r} (ORB-SLAM3 settings: Camera.fx/fy/cx/cy, Camera1.* "
                                     "and, for the right camera, Camera2.*)")
        v = s.number(pre + key)
        k[key] = _positive(path, pre + key, v, s.line(pre + key)) if key in ("fx", "fy") else v
    if cam_type == "KannalaBrandt8":
        model, names = "equidistant", ("k1", "k2", "k3", "k4")
    elif cam_type == "Rectified":  # ORB-SLAM3 v1.0: a rectified pair, no distortion
        model, names = "none", ()
    else:
        model, names = "radtan", ("k1", "k2", "p1", "p2") + (("k3",) if s.has(pre + "k3") else ())
    dist = tuple(s.number(pre + n) if s.has(pre + n) else 0.0 for n in names)
    if not any(dist):
        model, dist = "none", ()
    cam = PinholeCamera(size["width"], size["height"], k["fx"], k["fy"], k["cx"], k["cy"], model, dist)  # type: ignore[arg-type]
    return check_camera(cam, path, _where(s, pre))


def _read_opencv(path: Path) -> CameraFile:
    s = _Settings(path)
    pre = "Camera1." if s.has("Camera1.fx") else "Camera."
    size = {}
    for key in ("width", "height"):
        name = f"Camera.{key}"
        v = _positive(path, name, s.number(name), s.line(name)) if s.has(name) else 0.0
        if v != int(v):
            raise DatasetError(path, f"{name!r} must be a positive integer (pixels), got {v:g}", s.line(name))
        size[key] = int(v)
    cam_type = s.fs.getNode("Camera.type").string() if s.has("Camera.type") else "PinHole"
    if cam_type not in ("PinHole", "Pinhole", "", "KannalaBrandt8", "Rectified"):
        raise DatasetError(path, f"'Camera.type' {cam_type!r} not supported; expected PinHole, KannalaBrandt8 or "
                                 "Rectified", s.line("Camera.type"))
    cam = _opencv_camera(s, pre, cam_type, size)
    cam1 = _opencv_camera(s, "Camera2.", cam_type, size) if any(
        s.has(f"Camera2.{key}") for key in ("fx", "fy", "cx", "cy")) else None
    where = _where(s, pre)
    T01 = None
    for key in ("Stereo.T_c1_c2", "Stereo.b", "Camera.bf"):
        if s.has(key):
            where["baseline"] = (key, s.line(key))
            break
    if s.has("Stereo.T_c1_c2"):
        T01 = _rigid(path, "Stereo.T_c1_c2", s.matrix("Stereo.T_c1_c2"), s.line("Stereo.T_c1_c2"))
    elif s.has("Stereo.b"):
        T01 = _baseline_T(_positive(path, "Stereo.b", s.number("Stereo.b"), s.line("Stereo.b")))
    elif s.has("Camera.bf"):
        T01 = _baseline_T(_positive(path, "Camera.bf", s.number("Camera.bf"), s.line("Camera.bf")) / cam.fx)
    T_bc = None
    for key in ("IMU.T_b_c1", "Tbc"):
        if s.has(key):
            T_bc = _rigid(path, key, s.matrix(key), s.line(key))
            break
    imu = None
    if s.has("IMU.NoiseGyro"):
        keys = {"gyro_noise_density": "IMU.NoiseGyro", "accel_noise_density": "IMU.NoiseAcc",
                "gyro_random_walk": "IMU.GyroWalk", "accel_random_walk": "IMU.AccWalk", "rate_hz": "IMU.Frequency"}
        imu = ImuNoise(**{f: _positive(path, key, s.number(key), s.line(key)) for f, key in keys.items() if s.has(key)})
    depth_scale = _positive(path, "DepthMapFactor", s.number("DepthMapFactor"), s.line("DepthMapFactor")) \
        if s.has("DepthMapFactor") else None
    fps = s.number("Camera.fps") if s.has("Camera.fps") else None
    return CameraFile(path, cam, None, None, depth_scale, None, T01, fps, T_bc, imu, cam1, where=where,
                      where1=_where(s, "Camera2.") if cam1 is not None else None)
