"""A video file (anything OpenCV's FFmpeg backend reads) and a camera file.

    seq = VideoSequence("walk.mp4", camera="camera.yaml")

Frame times come from the container (``CAP_PROP_POS_MSEC`` of each frame, so a variable frame rate is kept),
or from ``fps`` when given. Opening the video reads through it once (demuxing and decoding, no colour
conversion) to list those times; frames are then decoded in order as the pipeline asks for them.
A video has no depth and no second view, so the sensor is mono.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vslam.data.camera_file import CAMERA_FILE_NAME, read_camera_file
from vslam.data.images import read_times_file
from vslam.data.types import Frame, Sequence
from vslam.errors import DatasetError

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".mts")


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise DatasetError(path, "unreadable video: OpenCV (FFmpeg) cannot open it; expected a video file such as "
                                 ".mp4, .avi or .mkv")
    return cap


class VideoSequence(Sequence):
    """Frames of the video at ``path``; intrinsics from ``camera`` (default: ``<video stem>.yaml``, else
    camera.yaml, beside the video). ``fps`` or ``times`` (one timestamp per line) replace the container's
    times. Frames: image (H,W,3) uint8 BGR, no depth, no ground truth."""

    def __init__(self, path: str | Path, camera: str | Path | None = None, sensor: str = "mono",
                 times: str | Path | None = None, fps: float = 0.0):
        self.path = Path(path).expanduser()
        if not self.path.is_file():
            raise DatasetError(self.path, "missing video file")
        if sensor != "mono":
            raise DatasetError(self.path, f"sensor {sensor!r} not available from a video (no depth, one view); "
                                          "use --sensor mono")
        self.name = self.path.stem
        self.sensor = "mono"
        cam_path = Path(camera).expanduser() if camera else next(
            (p for p in (self.path.with_suffix(".yaml"), self.path.parent / CAMERA_FILE_NAME) if p.is_file()),
            self.path.parent / CAMERA_FILE_NAME)
        cf = read_camera_file(cam_path)
        cap = _open(self.path)
        t_ms: list[float] = []
        while cap.grab():
            t_ms.append(cap.get(cv2.CAP_PROP_POS_MSEC))
        container_fps = cap.get(cv2.CAP_PROP_FPS)
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        if not t_ms:
            raise DatasetError(self.path, "unreadable video: OpenCV opened it but decoded no frame")
        if times:
            self._t = read_times_file(Path(times).expanduser(), len(t_ms), "video frames")
        elif fps or cf.fps:
            self._t = np.arange(len(t_ms), dtype=np.float64) / float(fps or cf.fps)  # type: ignore[arg-type]
        else:
            self._t = np.asarray(t_ms, np.float64) / 1e3
            if np.any(np.diff(self._t) <= 0):
                if not container_fps > 0:
                    raise DatasetError(self.path, "the container's frame times do not increase and it states no "
                                                  "frame rate; give --fps or --times")
                logger.warning("%s: container frame times do not increase; using its frame rate %.3f", self.path,
                               container_fps)
                self._t = np.arange(len(t_ms), dtype=np.float64) / container_fps
        self.camera_file = cf
        self.calibration = cf.calibration(width, height, "mono")
        self._cap: cv2.VideoCapture | None = None
        self._next = 0  # index of the frame the open capture decodes next

    def __getstate__(self) -> dict[str, Any]:  # sent to the front-end process: it opens its own capture
        state = self.__dict__.copy()
        state["_cap"], state["_next"] = None, 0
        return state

    def close(self) -> None:
        """Release the open capture (the next frame asked for opens it again)."""
        if self._cap is not None:
            self._cap.release()
            self._cap, self._next = None, 0

    def __len__(self) -> int:
        return len(self._t)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def _load(self, i: int) -> Frame | None:
        if self._cap is None:
            self._cap, self._next = _open(self.path), 0
        if i < self._next:  # backwards: seek (frame-exact for intra-only codecs; FFmpeg seeks to a keyframe)
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        else:  # forwards (stride, drop): demux and decode the frames between, exact for every codec
            for _ in range(i - self._next):
                if not self._cap.grab():
                    break
        ok, image = self._cap.read()
        self._next = i + 1
        if not ok or image is None:
            logger.warning("%s: frame %d does not decode; frame skipped", self.path, i)
            return None
        cam = self.calibration.cam0
        if image.shape[:2] != (cam.height, cam.width):
            logger.warning("%s: frame %d is %dx%d, the camera's is %dx%d; frame skipped", self.path, i,
                           image.shape[1], image.shape[0], cam.width, cam.height)
            return None
        if i + 1 == len(self._t):
            self.close()
        return Frame(index=i, timestamp=float(self._t[i]), image=image)


def is_video_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES
