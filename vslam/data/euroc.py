"""EuRoC MAV / TUM-VI reader (the ASL folder layout) behind the Sequence interface.

Layout (``mav0/`` inside the sequence folder)::

    cam0/data.csv  (#timestamp [ns],filename)   cam0/data/<ns>.png   cam0/sensor.yaml
    cam1/...       (stereo only)
    imu0/data.csv  (ns, w xyz rad/s, a xyz m/s^2)                     imu0/sensor.yaml
    state_groundtruth_estimate0/data.csv  (ns, p, q wxyz, v, bw, ba; BODY frame)  [EuRoC]
    mocap0/data.csv                       (ns, p, q wxyz; BODY frame)             [TUM-VI]

The body frame is the IMU frame (EuRoC: imu0 ``T_BS`` is the identity), so the
camera ``T_BS`` are ``T_body_cam``. Ground truth is of the body; the reader
turns it into cam0 poses, ``T_world_cam0 = T_world_body @ T_body_cam0``.

Timestamps are kept as int64 nanoseconds for exact cam0/cam1 pairing and
converted to float64 seconds (``ns * 1e-9``, ~0.3 us resolution at 1.4e9 s)
the same way for images, IMU and ground truth, so equal nanoseconds give equal
seconds and ``ImuSamples.between`` slices exactly.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from vslam.data.association import check as check_pairing
from vslam.data.association import no_pairs_text
from vslam.data.association import report as pairing_report
from vslam.data.calibration import check_calibration, check_camera, check_image_size, image_file_size
from vslam.data.textio import (check_increasing, check_unit_quaternions, read_rows, read_yaml_mapping, require_dir,
                               require_file, yaml_numbers)
from vslam.data.trajectory import Trajectory
from vslam.data.types import Calibration, DistortionModel, Frame, ImuNoise, ImuSamples, PinholeCamera, SensorKind, Sequence
from vslam.errors import DatasetError
from vslam.geometry.se3 import quat_wxyz_to_R

logger = logging.getLogger(__name__)

# ASL / Kalibr spellings -> our DistortionModel, with the coefficient counts each takes.
_DISTORTION_NAMES: dict[str, DistortionModel] = {
    "radial-tangential": "radtan",
    "radtan": "radtan",
    "equidistant": "equidistant",
    "equi": "equidistant",
    "fisheye": "equidistant",
    "none": "none",
}
_DISTORTION_COUNTS: dict[str, tuple[int, ...]] = {"radtan": (4, 5), "equidistant": (4,), "none": (0,)}


def parse_distortion_model(path: Path, name: object, line: int | None) -> DistortionModel:
    """ASL/Kalibr distortion name (``radial-tangential``, ``equidistant``, ...) -> DistortionModel."""
    model = _DISTORTION_NAMES.get(str(name).lower())
    if model is None:
        raise DatasetError(path, f"unknown distortion_model {name!r}; expected one of {', '.join(_DISTORTION_NAMES)}", line)
    return model


# ----------------------------------------------------------------------------- sensor.yaml


def read_camera_yaml(path: Path) -> tuple[PinholeCamera, np.ndarray]:
    """An ASL camera ``sensor.yaml`` -> (intrinsics, T_body_cam (4,4) from ``T_BS``)."""
    data, lines = read_yaml_mapping(path)
    model_name = data.get("camera_model", "pinhole")
    if model_name != "pinhole":
        raise DatasetError(path, f"camera_model {model_name!r} is not supported (only pinhole)", lines.get("camera_model"))
    w, h = yaml_numbers(path, data, lines, "resolution", 2)
    fu, fv, cu, cv = yaml_numbers(path, data, lines, "intrinsics", 4)
    if "distortion_model" not in data:
        raise DatasetError(path, "missing key 'distortion_model'")
    model = parse_distortion_model(path, data["distortion_model"], lines.get("distortion_model"))
    coeffs = yaml_numbers(path, data, lines, "distortion_coefficients", _DISTORTION_COUNTS[model]) if model != "none" else []
    for key, v in (("width", w), ("height", h)):
        if not (v > 0 and v == int(v)):
            raise DatasetError(path, f"resolution {key} = {v:g}: the image size must be a positive integer (pixels)",
                               lines.get("resolution"))
    camera = PinholeCamera(int(w), int(h), fu, fv, cu, cv, model, tuple(coeffs))
    return check_camera(camera, path, camera_where(lines)), read_T_BS(path, data, lines)


def camera_where(lines: dict[str, int]) -> dict[str, tuple[str, int | None]]:
    """How an ASL sensor.yaml names each camera field, and its line (for ``check_camera``'s errors)."""
    intr, res = lines.get("intrinsics"), lines.get("resolution")
    return {"fx": ("intrinsics fu", intr), "fy": ("intrinsics fv", intr), "cx": ("intrinsics cu", intr),
            "cy": ("intrinsics cv", intr), "width": ("resolution width", res), "height": ("resolution height", res),
            "distortion": ("distortion_coefficients", lines.get("distortion_coefficients"))}


def read_T_BS(path: Path, data: dict[str, Any], lines: dict[str, int]) -> np.ndarray:
    """The ``T_BS`` (sensor -> body) 4x4 of an ASL sensor.yaml, checked to be rigid."""
    block = data.get("T_BS")
    if not isinstance(block, dict):
        raise DatasetError(path, "missing key 'T_BS' (a mapping with rows, cols, data)", lines.get("T_BS"))
    key_line = {"data": lines["T_BS"]} if "T_BS" in lines else {}
    T = np.array(yaml_numbers(path, block, key_line, "data", 16)).reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise DatasetError(path, "T_BS is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)", lines.get("T_BS"))
    return T


def read_imu_yaml(path: Path, rate_from_data: float) -> ImuNoise:
    """imu0 ``sensor.yaml`` noise densities -> ImuNoise; defaults (EuRoC values) when absent, with a warning."""
    if not path.is_file():
        logger.warning("%s: missing; using EuRoC ADIS16448 noise defaults and the data rate %.1f Hz", path, rate_from_data)
        return ImuNoise(rate_hz=rate_from_data)
    data, lines = read_yaml_mapping(path)
    T = read_T_BS(path, data, lines) if "T_BS" in data else np.eye(4)
    if not np.allclose(T, np.eye(4), atol=1e-9):
        logger.warning("%s: imu0 T_BS is not the identity; vslam takes the IMU frame as the body frame", path)
    keys = {
        "gyroscope_noise_density": "gyro_noise_density",
        "gyroscope_random_walk": "gyro_random_walk",
        "accelerometer_noise_density": "accel_noise_density",
        "accelerometer_random_walk": "accel_random_walk",
        "rate_hz": "rate_hz",
    }
    values: dict[str, float] = {}
    for src, dst in keys.items():
        if src not in data:
            raise DatasetError(path, f"missing key {src!r}")
        v = data[src]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v) or v <= 0:
            raise DatasetError(path, f"{src!r} must be a positive number, got {v!r}", lines.get(src))
        values[dst] = float(v)
    return ImuNoise(**values)


# ----------------------------------------------------------------------------- CSV tables


def read_ns_table(
    path: Path, ncols: int, what: str, numeric_cols: int | None = None
) -> tuple[np.ndarray, np.ndarray, list[list[str]]]:
    """(line numbers (N,), int64 ns timestamps (N,), rows) of an ASL csv, time strictly increasing.

    The first column must be an integer nanosecond count (float64 cannot hold
    19-digit nanoseconds exactly); numeric_cols leading columns must be finite
    numbers (default: all).
    """
    require_file(path, what)
    lines, rows = read_rows(path, ncols, delimiter=",", numeric_cols=numeric_cols)
    ns = np.empty(len(rows), dtype=np.int64)
    for k, r in enumerate(rows):
        try:
            ns[k] = int(r[0])
        except ValueError:
            raise DatasetError(path, f"timestamp {r[0]!r} is not an integer nanosecond count", lines[k]) from None
    line_arr = np.asarray(lines, dtype=np.int64)
    check_increasing(path, ns, line_arr)
    return line_arr, ns, rows


def ns_to_s(ns: np.ndarray) -> np.ndarray:
    """int64 nanoseconds -> float64 seconds (one conversion for every stream, see module doc)."""
    return np.asarray(ns, dtype=np.int64) * 1e-9


@dataclass
class BodyGroundTruth:
    """EuRoC ground-truth state of the body (IMU) frame at its native rate.

    trajectory: T_world_body poses (N,4,4), times (N,) s.
    velocity: (N,3) m/s in the world frame; gyro_bias (N,3) rad/s; accel_bias (N,3) m/s^2.
    The three arrays are None for pose-only ground truth (TUM-VI mocap0).
    """

    trajectory: Trajectory
    velocity: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    accel_bias: np.ndarray | None = None


def read_body_groundtruth(mav0: Path) -> BodyGroundTruth | None:
    """state_groundtruth_estimate0 (EuRoC, 17 columns) or mocap0 (TUM-VI, 8 columns), else None."""
    for folder, ncols in (("state_groundtruth_estimate0", 17), ("mocap0", 8)):
        path = mav0 / folder / "data.csv"
        if not path.is_file():
            continue
        lines, ns, rows = read_ns_table(path, ncols, "ground-truth file")
        if not rows:
            raise DatasetError(path, "ground-truth file has no rows")
        v = np.array([[float(x) for x in r[1:]] for r in rows], dtype=np.float64)
        check_unit_quaternions(path, v[:, 3:7], np.asarray(lines), first_col=5)
        poses = np.tile(np.eye(4), (len(v), 1, 1))
        poses[:, :3, :3] = quat_wxyz_to_R(v[:, 3:7])
        poses[:, :3, 3] = v[:, 0:3]
        traj = Trajectory(ns_to_s(ns), poses)
        if ncols == 17:
            return BodyGroundTruth(traj, v[:, 7:10], v[:, 10:13], v[:, 13:16])
        return BodyGroundTruth(traj)
    return None


def read_imu_csv(path: Path) -> tuple[ImuSamples, float]:
    """imu0/data.csv -> (ImuSamples in seconds, median sample period s); a NaN or malformed row is an error naming its line.

    The samples keep their file and line numbers: readings that parse but cannot be believed (out of the
    sensor's range, spikes) are rejected later, by ``vslam.inertial.gate``, which names them.
    """
    lines, ns, rows = read_ns_table(path, 7, "IMU file")
    v = np.array([[float(x) for x in r[1:]] for r in rows], dtype=np.float64).reshape(-1, 6)
    period = float(np.median(np.diff(ns))) * 1e-9 if len(ns) > 1 else 0.005
    return ImuSamples(ns_to_s(ns), v[:, 0:3], v[:, 3:6], str(path), lines), period


# ----------------------------------------------------------------------------- the sequence


@dataclass
class _CameraStream:
    """One camera's listing: ns (N,), files (N,), the data.csv lines (N,)."""

    csv: Path
    ns: np.ndarray
    files: list[Path]
    lines: np.ndarray


def _read_camera_stream(cam_dir: Path) -> _CameraStream:
    csv = cam_dir / "data.csv"
    lines, ns, rows = read_ns_table(csv, 2, "camera list data.csv", numeric_cols=1)
    return _CameraStream(csv, ns, [cam_dir / "data" / r[1] for r in rows], lines)


class EurocSequence(Sequence):
    """EuRoC MAV or TUM-VI sequence in the ASL layout.

    path: the sequence folder holding ``mav0/``, or ``mav0`` itself.
    sensor: "stereo" (cam0 + cam1, frames whose timestamp is in both lists)
        or "mono" (cam0 only).
    max_diff: seconds; a frame gets the ground-truth pose nearest in time
        within this, else None.

    Frames carry grayscale uint8 images and ``Frame.imu`` = the IMU samples
    with t in (previous frame's t, this t]; when iterating, "previous" is the
    previous frame yielded, so a skipped undecodable frame's samples pass to
    the next one. The first frame has no previous frame; it gets the samples
    in (t0 - one IMU period, t0] (the sample at or just before t0 if there is
    one, else none), so that a filter can start from a measurement at t0
    without integrating over time before the sequence starts.
    """

    def __init__(self, path: str | Path, sensor: str = "stereo", max_diff: float = 0.01):
        root = require_dir(Path(path), "EuRoC sequence")
        self.mav0 = root if (root / "cam0").is_dir() and not (root / "mav0").is_dir() else root / "mav0"
        require_dir(self.mav0, "mav0 (EuRoC/TUM-VI layout)")
        if sensor not in ("stereo", "mono"):
            raise DatasetError(root, f"sensor {sensor!r} not available for EuRoC/TUM-VI; use 'stereo' or 'mono'")
        self.path = root
        self.name = (root.parent if root.name == "mav0" else root).name
        self.sensor = cast(SensorKind, sensor)
        self.max_diff = float(max_diff)
        self._right: list[Path] | None = None  # cam1 images, stereo only

        cam0_model, T_b_c0, cam1_model, T_b_c1 = self._open_cameras()
        noise = self._open_imu()
        self.calibration = Calibration(cam0=cam0_model, cam1=cam1_model, T_body_cam0=T_b_c0, T_body_cam1=T_b_c1, imu=noise)

        # A ground-truth problem is raised by groundtruth(), after a run has written its trajectory: it must
        # not stop SLAM, which does not need the ground truth.
        self._gt_error: DatasetError | None = None
        try:
            self._gt_body = read_body_groundtruth(self.mav0)
        except DatasetError as e:
            self._gt_body, self._gt_error = None, e
        self._gt_cam: Trajectory | None = None
        if self._gt_body is not None:
            self._gt_cam = Trajectory(self._gt_body.trajectory.timestamps, self._gt_body.trajectory.poses @ T_b_c0)
            self._gt_idx = self._gt_cam.nearest(self._t, self.max_diff)
        else:
            self._gt_idx = np.full(len(self._t), -1, dtype=np.int64)

    def _open_cameras(self) -> tuple[PinholeCamera, np.ndarray, PinholeCamera | None, np.ndarray | None]:
        """Read cam0 (and cam1 for stereo) lists and sensor.yaml; keep the frames both cameras list."""
        cam0_dir = require_dir(self.mav0 / "cam0", "cam0")
        cam0 = _read_camera_stream(cam0_dir)
        if len(cam0.ns) == 0:
            raise DatasetError(cam0.csv, "lists no images")
        cam0_model, T_b_c0 = read_camera_yaml(cam0_dir / "sensor.yaml")
        keep0 = np.arange(len(cam0.ns))
        cam1_model: PinholeCamera | None = None
        T_b_c1: np.ndarray | None = None
        if self.sensor == "stereo":
            cam1_dir = require_dir(self.mav0 / "cam1", "cam1 (needed for sensor='stereo')")
            cam1 = _read_camera_stream(cam1_dir)
            cam1_model, T_b_c1 = read_camera_yaml(cam1_dir / "sensor.yaml")
            keep0 = np.flatnonzero(np.isin(cam0.ns, cam1.ns))
            keep1 = np.searchsorted(cam1.ns, cam0.ns[keep0])
            t0, t1 = ns_to_s(cam0.ns), ns_to_s(cam1.ns)
            if len(keep0) == 0:
                raise DatasetError(cam1.csv, no_pairs_text(t0, t1, "cam0", "cam1", "with the same timestamp",
                                                           "cam1/data.csv") + "; check the timestamps, or run with --sensor mono")
            names = [str(f.relative_to(self.mav0)) for f in cam0.files]
            self.association = pairing_report("left-right", t0, names, t1, keep0, keep1, 0.0,
                                              "no cam1 image with the same timestamp", unpaired_kept=False)
            dropped = (len(cam0.ns) - len(keep0), len(cam1.ns) - len(keep1))
            if any(dropped):
                logger.info("%s: %d cam0 and %d cam1 images have no partner; stereo keeps %d frames", self.mav0, *dropped, len(keep0))
            check_pairing(self.association, t0, t1, keep0, keep1, cam0.csv, "cam0 (left)", "cam1 (right)", logger)
            # Existence is checked only for the frames kept: EuRoC cam lists may
            # name unpaired images that the archive does not hold.
            _check_listed(cam1, keep1)
            self._right = [cam1.files[i] for i in keep1]
            check_image_size(cam1_model, image_file_size(self._right[0]), self._right[0],
                             f"{cam1_dir / 'sensor.yaml'} (resolution)")
            lines = read_yaml_mapping(cam1_dir / "sensor.yaml")[1]
            check_calibration(Calibration(cam0=cam0_model, cam1=cam1_model, T_body_cam0=T_b_c0, T_body_cam1=T_b_c1),
                              cam0_dir / "sensor.yaml", path1=cam1_dir / "sensor.yaml",
                              baseline=("T_BS (the baseline from cam0/sensor.yaml's T_BS)", lines.get("T_BS")))
        _check_listed(cam0, keep0)
        self._t = ns_to_s(cam0.ns[keep0])
        self._left = [cam0.files[i] for i in keep0]
        # the first image must be of the declared size (a later one that is not is skipped, see _imread_gray)
        check_image_size(cam0_model, image_file_size(self._left[0]), self._left[0],
                         f"{cam0_dir / 'sensor.yaml'} (resolution)")
        return cam0_model, T_b_c0, cam1_model, T_b_c1

    def _open_imu(self) -> ImuNoise | None:
        """imu0/ (optional): all samples, the noise model, and the sample period for the first frame's slice."""
        self._imu: ImuSamples | None = None
        self._imu_period = 0.0
        if not (self.mav0 / "imu0").is_dir():
            return None
        self._imu, dt = read_imu_csv(self.mav0 / "imu0" / "data.csv")
        noise = read_imu_yaml(self.mav0 / "imu0" / "sensor.yaml", 1.0 / dt)
        self._imu_period = 1.0 / noise.rate_hz
        return noise

    # -- Sequence interface ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._t)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def __iter__(self) -> Iterator[Frame]:
        # A frame after a skipped (undecodable) one also gets the skipped frame's
        # IMU samples, so the IMU stream reaching the consumer has no gap.
        t_prev: float | None = None
        for i in range(len(self)):
            frame = self._load(i, t_prev)
            if frame is not None:
                t_prev = frame.timestamp
                yield frame

    def groundtruth(self) -> Trajectory | None:
        """T_world_cam0 at the ground-truth rate (body poses @ T_body_cam0); DatasetError when the file is
        malformed."""
        if self._gt_error is not None:
            raise self._gt_error
        return self._gt_cam

    def imu(self) -> ImuSamples | None:
        """Every IMU sample of the recording (it may span more than the listed frames)."""
        return self._imu

    # -- extras ------------------------------------------------------------------------

    def groundtruth_body(self) -> BodyGroundTruth | None:
        """Ground truth of the body (IMU) frame with velocities and biases (EuRoC), for IMU work."""
        if self._gt_error is not None:
            raise self._gt_error
        return self._gt_body

    def frame_pose(self, i: int) -> np.ndarray | None:
        """Ground-truth T_world_cam0 (4,4) of frame i without decoding its images, or None."""
        j = int(self._gt_idx[i])
        return None if j < 0 or self._gt_cam is None else self._gt_cam.poses[j].copy()

    def frame_imu(self, i: int, t_prev: float | None = None) -> ImuSamples | None:
        """IMU samples in (t_prev, t_i]; t_prev defaults to the listed previous frame's time
        (one IMU period before t_0 for the first frame, see the class doc). None without an IMU."""
        if self._imu is None:
            return None
        if t_prev is None:
            t_prev = float(self._t[i - 1]) if i > 0 else float(self._t[0]) - self._imu_period
        return self._imu.between(t_prev, float(self._t[i]))

    def frame(self, i: int) -> Frame:
        """Frame i with its images decoded; DatasetError if an image does not decode."""
        frame = self._load(i)
        if frame is None:
            raise DatasetError(self._left[i], "image does not decode")
        return frame

    def _load(self, i: int, t_prev: float | None = None) -> Frame | None:
        left = _imread_gray(self._left[i], self.calibration.cam0)
        right = _imread_gray(self._right[i], self.calibration.cam1) if self._right is not None else None
        if left is None or (self._right is not None and right is None):
            return None
        return Frame(
            index=i,
            timestamp=float(self._t[i]),
            image=left,
            right=right,
            imu=self.frame_imu(i, t_prev),
            T_world_cam=self.frame_pose(i),
        )


def _check_listed(stream: _CameraStream, keep: np.ndarray) -> None:
    for i in keep:
        if not stream.files[i].is_file():
            raise DatasetError(stream.csv, f"listed image {stream.files[i]} does not exist", int(stream.lines[i]))


def _imread_gray(path: Path, cam: PinholeCamera | None) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        logger.warning("%s: image does not decode; frame skipped", path)
    elif cam is not None and img.shape != (cam.height, cam.width):
        logger.warning("%s: image is %dx%d, the camera's is %dx%d; frame skipped", path, img.shape[1], img.shape[0],
                       cam.width, cam.height)
        return None
    return img


def is_euroc_layout(path: Path) -> bool:
    """True for a folder holding ``mav0/`` or for ``mav0`` itself (``cam0/data.csv``)."""
    return (path / "mav0").is_dir() or (path / "cam0" / "data.csv").is_file()
