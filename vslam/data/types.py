"""The one interface every dataset reader implements: a Sequence yielding Frames.

Frames carry what the sensors recorded at one camera timestamp (image, depth,
right image, the IMU samples since the previous frame) plus what the dataset
knows about it (ground-truth pose, dynamic mask). Arrays are numpy; units are
metres, seconds and radians.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Iterator, Literal

import cv2
import numpy as np

DistortionModel = Literal["none", "radtan", "equidistant"]
SensorKind = Literal["rgbd", "stereo", "mono"]


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """Pinhole intrinsics with optional lens distortion.

    ``distortion`` is (k1, k2, p1, p2[, k3]) for ``radtan`` (OpenCV order) and
    (k1, k2, k3, k4) for ``equidistant`` (OpenCV fisheye / Kalibr).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: DistortionModel = "none"
    distortion: tuple[float, ...] = ()

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def is_distorted(self) -> bool:
        return self.distortion_model != "none" and any(abs(c) > 0 for c in self.distortion)

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """(N,3) camera-frame points -> (N,2) ideal (undistorted) pixel coordinates."""
        pts = np.asarray(pts_cam, dtype=np.float64)
        z = pts[:, 2]
        return np.stack([self.fx * pts[:, 0] / z + self.cx, self.fy * pts[:, 1] / z + self.cy], axis=1)

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(N,2) ideal pixels and (N,) depths (metres, along z) -> (N,3) camera-frame points."""
        uv = np.asarray(uv, dtype=np.float64)
        d = np.asarray(depth, dtype=np.float64)
        x = (uv[:, 0] - self.cx) / self.fx * d
        y = (uv[:, 1] - self.cy) / self.fy * d
        return np.stack([x, y, d], axis=1)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """(N,2) raw pixels -> (N,2) ideal pixels of the same K (identity if undistorted)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if not self.is_distorted or len(uv) == 0:
            return uv.reshape(-1, 2).copy()
        D = np.asarray(self.distortion, dtype=np.float64)
        if self.distortion_model == "equidistant":
            out = cv2.fisheye.undistortPoints(uv, self.K, D, P=self.K)
        else:
            out = cv2.undistortPoints(uv, self.K, D, P=self.K)
        return out.reshape(-1, 2)


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities (Kalibr / EuRoC sensor.yaml convention)."""

    gyro_noise_density: float = 1.6968e-4  # rad/s/sqrt(Hz)
    gyro_random_walk: float = 1.9393e-5  # rad/s^2/sqrt(Hz)
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accel_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)
    rate_hz: float = 200.0


def _eye4() -> np.ndarray:
    return np.eye(4)


@dataclass(frozen=True, eq=False)
class Calibration:
    """Cameras, their extrinsics in the body (IMU) frame, and IMU noise.

    Without an IMU the body frame is cam0 (``T_body_cam0`` = identity).
    """

    cam0: PinholeCamera
    cam1: PinholeCamera | None = None
    T_body_cam0: np.ndarray = field(default_factory=_eye4)
    T_body_cam1: np.ndarray | None = None
    imu: ImuNoise | None = None
    depth_scale: float | None = None  # raw depth units per metre (TUM: 5000); Frame.depth is already metres

    @property
    def T_cam0_cam1(self) -> np.ndarray | None:
        if self.T_body_cam1 is None:
            return None
        from vslam.geometry.se3 import inv_T

        return inv_T(self.T_body_cam0) @ self.T_body_cam1

    @property
    def baseline(self) -> float | None:
        """Stereo baseline in metres (distance between the two camera centres)."""
        T = self.T_cam0_cam1
        return None if T is None else float(np.linalg.norm(T[:3, 3]))


@dataclass
class ImuSamples:
    """IMU readings in the body frame: t (N,) s, gyro (N,3) rad/s, accel (N,3) m/s^2 (specific force).

    source / line: where the readings came from, so that a rejected one can be named (the file, and (N,) int64
    1-based line numbers in it counting the header); "" / None for generated data.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    source: str = ""
    line: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def empty() -> ImuSamples:
        return ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))

    def between(self, t0: float, t1: float) -> ImuSamples:
        """Samples with t0 < t <= t1 (the samples a frame at t1 owns after a frame at t0)."""
        lo = np.searchsorted(self.t, t0, side="right")
        hi = np.searchsorted(self.t, t1, side="right")
        line = self.line[lo:hi] if self.line is not None else None
        return ImuSamples(self.t[lo:hi], self.gyro[lo:hi], self.accel[lo:hi], self.source, line)


@dataclass
class Frame:
    """Everything recorded at one camera timestamp.

    image: (H,W) uint8 grey or (H,W,3) uint8 BGR, raw (distorted) left/colour image.
    depth: (H,W) float32 metres, 0 where invalid (RGB-D, synthetic).
    right: right stereo image, same format as ``image``.
    imu: samples with t in (previous frame's t, this t].
    T_world_cam: ground-truth pose of cam0 (4,4), None where unknown.
    dynamic_mask: (H,W) bool, True on moving objects (synthetic only).
    boxes: (K,4) float x1,y1,x2,y2 pixels of moving objects (synthetic only).
    """

    index: int
    timestamp: float
    image: np.ndarray
    depth: np.ndarray | None = None
    right: np.ndarray | None = None
    imu: ImuSamples | None = None
    T_world_cam: np.ndarray | None = None
    dynamic_mask: np.ndarray | None = None
    boxes: np.ndarray | None = None


@dataclass
class Association:
    """How a reader paired a second image stream with its frames when the sequence was opened
    (``Sequence.association``; ``vslam.data.association`` checks it and warns).

    kind: "rgb-depth" (TUM, image folder, bag: nearest time within ``max_offset_s``, one to one) or
        "left-right" (EuRoC stereo: the same timestamp).
    inputs: images of the frame stream listed (rgb / left); partners: images of the other stream listed.
    paired: inputs given a partner. ``dropped``: (file, or time for a bag, why) of each input given none.
    unpaired_kept: True where an input without a partner stays a frame (rgb-depth: a frame without depth),
        False where it is not a frame (left-right: ``len(sequence) == paired``).
    max_offset_s: the pairing tolerance (0: equal times). median_offset_s: median of (partner - input) time
        over the pairs. shift_s: a constant shift of the partner stream's times that the reader suspects (and
        warned about), else None.
    """

    kind: Literal["rgb-depth", "left-right"]
    inputs: int
    paired: int
    dropped: list[tuple[str, str]] = field(default_factory=list)
    partners: int = 0
    unpaired_kept: bool = True
    max_offset_s: float = 0.0
    median_offset_s: float | None = None
    shift_s: float | None = None

    @property
    def drop_rate(self) -> float:
        """Fraction of the inputs left without a partner."""
        return len(self.dropped) / self.inputs if self.inputs else 0.0

    def summary(self) -> str:
        """One line for a run's summary, e.g. ``rgb-depth pairing: 40 rgb images, 37 with depth within 0.02 s,
        3 without (kept as frames without depth; first: rgb/1.png, no depth image within 0.02 s)``."""
        a, b = ("rgb", "depth") if self.kind == "rgb-depth" else ("left", "right")
        within = f"within {self.max_offset_s:g} s" if self.max_offset_s > 0 else "at the same time"
        text = f"{self.kind} pairing: {self.inputs} {a} images, {self.paired} with {b} {within}"
        if self.dropped:
            fate = "kept as frames without depth" if self.unpaired_kept else "dropped"
            text += f", {len(self.dropped)} without ({fate}; first: {self.dropped[0][0]}, {self.dropped[0][1]})"
        if self.shift_s is not None:
            text += f"; {b} times look shifted by {self.shift_s:+.3f} s"
        return text


class Sequence(abc.ABC):
    """A recorded (or generated) sequence; iterate it to get Frames in time order.

    Implementations load images lazily, so a Sequence is cheap to open; they
    raise DatasetError at open time for structural problems (missing files,
    bad columns, non-monotonic time) and warn-and-skip a frame whose image
    does not decode.
    """

    name: str
    sensor: SensorKind
    calibration: Calibration
    # how a second stream (depth, right images) was paired with the frames when the sequence opened; None for
    # a reader that pairs nothing (or a sensor that needs no second stream)
    association: Association | None = None
    # median valid depth (metres, after the reader's depth scale) of the first paired depth image, measured when
    # an RGB-D sequence opens (vslam.data.association.check_depth_image); None when not measured
    depth_median_m: float | None = None

    @abc.abstractmethod
    def __len__(self) -> int:
        """Number of frames listed (a frame that fails to decode is still counted)."""

    @abc.abstractmethod
    def timestamps(self) -> np.ndarray:
        """(N,) float64 seconds of the listed frames."""

    def __iter__(self) -> Iterator[Frame]:
        """Frames in time order; a frame whose files do not decode is skipped (``_load`` logs why)."""
        for i in range(len(self)):
            frame = self._load(i)
            if frame is not None:
                yield frame

    def _load(self, i: int) -> Frame | None:
        """Frame i decoded, or None when its files do not decode. Readers override this (or ``__iter__``)."""
        raise NotImplementedError

    @property
    def skipped(self) -> list[tuple[int, str]]:
        """(frame index, why) of the frames this reader skipped so far because they do not decode (the video
        and image-folder readers fill it: a video's undecodable frames when it is opened, an image file when
        it is read; each was also logged as a warning). The frames read in another process (the front-end
        process) are counted there, not here."""
        return self.__dict__.setdefault("_skipped", [])

    def groundtruth(self) -> "Trajectory | None":
        """Ground-truth trajectory of cam0 at its native rate, or None."""
        return None

    def imu(self) -> ImuSamples | None:
        """All IMU samples of the sequence, or None."""
        return None

    def close(self) -> None:
        """Release what the reader holds open (a video capture, a bag reader, a camera). Safe to call twice;
        the default holds nothing. Iterating again after ``close`` reopens what it needs (a live camera: the
        device again)."""

    def __enter__(self) -> "Sequence":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


from vslam.data.trajectory import Trajectory  # noqa: E402  (re-exported for type hints)
