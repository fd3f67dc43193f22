"""Every N-th frame, or frame ranges cut out, of any sequence (``dataset.stride``, ``dataset.drop``).

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

    def __init__(self, base: Sequence, indices: np.ndarray):
        self.base = base
        self.indices = np.asarray(indices, np.int64)
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
            yield frame


def select_frames(seq: Sequence, stride: int = 1, drop: tuple[tuple[int, int], ...] = ()) -> Sequence:
    """``seq`` itself when nothing is selected away, else its ``Subsequence``."""
    if stride == 1 and not drop:
        return seq
    return Subsequence(seq, kept_indices(len(seq), stride, drop))
