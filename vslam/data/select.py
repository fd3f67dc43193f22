"""Every N-th frame, or frame ranges cut out, of any sequence (``dataset.stride``, ``dataset.drop``), and its
images JPEG-compressed (``dataset.jpeg_quality``: a recording stored lossy, or streamed over a weak link).

A low frame rate, a keyframe-only log or a dropped camera are one option away on every reader: the frames keep
their original index (stats.csv rows point into the recording), and a frame after a gap carries every IMU
sample since the previous kept frame, so the inertial stream has no hole where the images have one.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from vslam.data.types import Frame, ImuSamples, Sequence
from vslam.errors import ConfigError


def kept_indices(n: int, stride: int = 1, drop: tuple[tuple[int, int], ...] = ()) -> np.ndarray:
    """Indices 0..n-1 that are multiples of ``stride`` and outside every inclusive ``drop`` range."""
    if stride < 1:
        raise ConfigError(f"dataset.stride must be at least 1, got {stride}")
    keep = np.zeros(n, bool)
    keep[::stride] = True
    for lo, hi in drop:
        if not 0 <= lo <= hi:
            raise ConfigError(f"dataset.drop ranges are [first, last] frame indices with 0 <= first <= last, got {[lo, hi]}")
        keep[lo:hi + 1] = False
    return np.flatnonzero(keep)


class Subsequence(Sequence):
    """The frames of ``base`` at ``indices`` (increasing), in order."""

    def __init__(self, base: Sequence, indices: np.ndarray, jpeg_quality: int = 0):
        self.base = base
        self.indices = np.asarray(indices, np.int64)
        self.jpeg_quality = jpeg_quality  # 0: the images as read
        self.name = base.name
        self.sensor = base.sensor
        self.calibration = base.calibration
        self.association = base.association  # of the whole recording, as the reader paired it

    def __len__(self) -> int:
        return len(self.indices)

    def timestamps(self) -> np.ndarray:
        return self.base.timestamps()[self.indices]

    def groundtruth(self):
        return self.base.groundtruth()

    def imu(self) -> ImuSamples | None:
        get = getattr(self.base, "imu", None)
        return get() if callable(get) else None

    def close(self) -> None:
        self.base.close()

    @property
    def skipped(self) -> list[tuple[int, str]]:
        return self.base.skipped

    def _base_frame(self, i: int) -> Frame | None:
        # readers with ``_load`` warn and return None for a frame that does not decode; the synthetic one renders
        if type(self.base)._load is not Sequence._load:
            return self.base._load(int(i))
        return self.base.frame(int(i))  # type: ignore[attr-defined]

    def __iter__(self) -> Iterator[Frame]:
        imu = self.imu()
        t_prev: float | None = None
        for i in self.indices:
            frame = self._base_frame(int(i))
            if frame is None:
                continue
            if imu is not None and t_prev is not None:
                frame.imu = imu.between(t_prev, frame.timestamp)
            t_prev = frame.timestamp
            if self.jpeg_quality:
                frame.image = jpeg_roundtrip(frame.image, self.jpeg_quality)
                if frame.right is not None:
                    frame.right = jpeg_roundtrip(frame.right, self.jpeg_quality)
            yield frame


def check_jpeg_quality(q: int) -> int:
    if not (q == 0 or 1 <= q <= 100):
        raise ConfigError(f"dataset.jpeg_quality must be 0 (images as read) or a JPEG quality 1-100, got {q}")
    return q


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` (grey or BGR uint8) JPEG-encoded at ``quality`` and decoded again (OpenCV's libjpeg)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)


def select_frames(seq: Sequence, stride: int = 1, drop: tuple[tuple[int, int], ...] = (),
                  jpeg_quality: int = 0) -> Sequence:
    """``seq`` itself when nothing is selected away or recompressed, else its ``Subsequence``."""
    if stride == 1 and not drop and not check_jpeg_quality(jpeg_quality):
        return seq
    return Subsequence(seq, kept_indices(len(seq), stride, drop), jpeg_quality)
