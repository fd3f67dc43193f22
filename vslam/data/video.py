"""A video file (anything OpenCV's FFmpeg backend reads) and a camera file.

    seq = VideoSequence("walk.mp4", camera="camera.yaml")

Frame times come from the container (``CAP_PROP_POS_MSEC`` of each frame, so a variable frame rate is kept),
or from ``fps`` when given. Opening the video reads through it once (demuxing and decoding, no colour
conversion) to list those times; frames are then decoded in order as the pipeline asks for them.
A video has no depth and no second view, so the sensor is mono.

A frame that does not decode (a damaged packet) does not end the video: the read is retried past it, the lost
frames (counted from the failed reads, and from the gap in the container's times when it states a frame rate)
keep their place in the frame list, are warned about once when the video is opened, and are listed in
``skipped``; iterating skips them. After ``MAX_FAILED_READS`` failed reads in a row the reader stops, and
says how many of the frames the container declares were decoded when that is fewer. No frame decoding at all
is an error.
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

MAX_FAILED_READS = 25  # failed reads in a row that end the video (the end of the stream fails them all at once)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".mts")


def _open(path: Path) -> cv2.VideoCapture:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise DatasetError(path, "unreadable video: OpenCV (FFmpeg) cannot open it; expected a video file such as "
                                 ".mp4, .avi or .mkv")
    return cap


def _grab(cap: cv2.VideoCapture) -> tuple[bool, int]:
    """Demux and decode the next frame that decodes: (decoded, failed reads before it), at most
    ``MAX_FAILED_READS`` failed reads in a row."""
    failed = 0
    while not cap.grab():
        failed += 1
        if failed >= MAX_FAILED_READS:
            return False, failed
    return True, failed


def _ranges(idx: list[int]) -> str:
    """[3, 4, 5, 9] -> "3-5, 9"."""
    out, start = [], 0
    for k in range(1, len(idx) + 1):
        if k == len(idx) or idx[k] != idx[k - 1] + 1:
            out.append(f"{idx[start]}" if k - 1 == start else f"{idx[start]}-{idx[k - 1]}")
            start = k
    return ", ".join(out)


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
        declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))  # 0 or less when the container does not say
        container_fps = cap.get(cv2.CAP_PROP_FPS)
        t_ms: list[float] = []  # container time of each frame that decodes
        index: list[int] = []  # its place among the container's frames (the lost ones counted)
        lost: list[int] = []  # the places of frames that do not decode
        while True:
            ok, failed = _grab(cap)
            if not ok:
                break
            t = cap.get(cv2.CAP_PROP_POS_MSEC)
            n_lost = failed
            if failed and container_fps > 0 and t_ms:  # the gap in the times says how many frames the failed reads
                # took; before the first decoded frame the container's start time is unknown (not always 0)
                gap = t - t_ms[-1]
                n_lost = max(failed, int(round(gap * container_fps / 1e3)) - 1)
            nxt = index[-1] + 1 if index else 0
            lost.extend(range(nxt, nxt + n_lost))
            index.append(nxt + n_lost)
            t_ms.append(t)
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()
        if not t_ms:
            says = f" (the container declares {declared} frames)" if declared > 0 else ""
            raise DatasetError(self.path, f"unreadable video: OpenCV opened it but decoded no frame{says}")
        n = index[-1] + 1
        if lost:
            logger.warning("%s: frame%s %s (%d of %d) do%s not decode; skipped", self.path, "s" if len(lost) > 1 else "",
                           _ranges(lost), len(lost), n, "" if len(lost) > 1 else "es")
            self.skipped.extend((j, f"video frame {j} does not decode") for j in lost)
        if declared > n:  # the reads failed MAX_FAILED_READS times in a row before the declared end
            logger.warning("%s: the container declares %d frames but %d were read (%d reads in a row failed after "
                           "frame %d); the %d missing are skipped", self.path, declared, n, MAX_FAILED_READS, n - 1,
                           declared - n)
            self.skipped.extend((j, f"video frame {j} not read ({MAX_FAILED_READS} reads in a row failed after frame "
                                    f"{n - 1})") for j in range(n, declared))
        self._ordinal = np.full(n, -1, np.int64)  # frame -> its place among the frames that decode, -1: lost
        self._ordinal[index] = np.arange(len(index))
        self._pts_ms = np.full(n, np.nan)
        self._pts_ms[index] = t_ms
        if times:
            self._t = read_times_file(Path(times).expanduser(), n, "video frames")
        elif fps or cf.fps:
            self._t = np.arange(n, dtype=np.float64) / float(fps or cf.fps)  # type: ignore[arg-type]
        else:
            self._t = np.interp(np.arange(n), index, t_ms) / 1e3  # a lost frame: between its neighbours
            if index[0] > 0:  # lost before the first frame that decodes (counted from the container's rate)
                period = 1e3 / container_fps if container_fps > 0 else \
                    float(np.median(np.diff(t_ms))) if len(t_ms) > 1 else 1e3 / 30
                self._t[: index[0]] = (t_ms[0] - (index[0] - np.arange(index[0])) * period) / 1e3
            if np.any(np.diff(self._t) <= 0):
                if not container_fps > 0:
                    raise DatasetError(self.path, "the container's frame times do not increase and it states no "
                                                  "frame rate; give --fps or --times")
                logger.warning("%s: container frame times do not increase; using its frame rate %.3f", self.path,
                               container_fps)
                self._t = np.arange(n, dtype=np.float64) / container_fps
        self.camera_file = cf
        self.calibration = cf.calibration(width, height, "mono", image=self.path)
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
        k = int(self._ordinal[i])  # the k-th frame that decodes; -1: it does not (warned and counted at open)
        if k < 0:
            return None
        if self._cap is None:
            self._cap, self._next = _open(self.path), 0
        if k < self._next:  # backwards: seek (frame-exact for intra-only codecs; FFmpeg seeks to a keyframe)
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, i)
        else:  # forwards (stride, drop): demux and decode the frames between, exact for every codec
            for _ in range(k - self._next):  # past lost frames as the scan went past them
                if not _grab(self._cap)[0]:
                    break
        ok = _grab(self._cap)[0]
        image = self._cap.retrieve()[1] if ok else None
        self._next = k + 1
        if image is None:
            logger.warning("%s: frame %d does not decode; frame skipped", self.path, i)
            self.skipped.append((i, f"video frame {i} does not decode"))
            return None
        pts = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        if abs(pts - self._pts_ms[i]) > 0.5 and not getattr(self, "_warned_pts", False):
            self._warned_pts = True  # the decoder went another way than when the video was opened: say so once
            logger.warning("%s: frame %d decoded at %.1f ms, listed at %.1f ms when the video was opened; frames "
                           "from here may be off by the difference", self.path, i, pts, self._pts_ms[i])
        cam = self.calibration.cam0
        if image.shape[:2] != (cam.height, cam.width):
            logger.warning("%s: frame %d is %dx%d, the camera's is %dx%d; frame skipped", self.path, i,
                           image.shape[1], image.shape[0], cam.width, cam.height)
            self.skipped.append((i, f"video frame {i} is {image.shape[1]}x{image.shape[0]}"))
            return None
        if i + 1 == len(self._t):
            self.close()
        return Frame(index=i, timestamp=float(self._t[i]), image=image)


def is_video_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES
