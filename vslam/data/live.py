"""A live camera: an OpenCV device index or stream URL, an Intel RealSense (colour + aligned depth), or a video
file replayed as if it were a camera (how the live path is tested).

    seq = LiveSequence("0", camera="webcam.yaml")                       # /dev/video0
    seq = LiveSequence("rtsp://10.0.0.5/stream", camera="ipcam.yaml")
    seq = LiveSequence("realsense", sensor="rgbd")                       # pip install 'vslam[realsense]'
    seq = LiveSequence("clip.avi", camera="clip.yaml", config=LiveConfig(realtime=True))

A grabber thread reads frames as fast as the source gives them, stamps them and puts them in a bounded queue
(``LiveConfig.queue``, default 2 frames). When the tracker is slower than the camera, the oldest queued frame
is dropped, so the tracker always gets a recent frame instead of falling further and further behind. Frames
are numbered in grab order, dropped ones included: ``Frame.index`` gaps are the dropped frames (the pipeline's
stats.csv ``dropped`` column). Recorded inputs (every other reader) never drop.

A live sequence has no length: iterate it until the stream ends (a video file, a closed stream, a camera that
gives no frame for ``LiveConfig.timeout`` seconds), until ``stop()`` (Ctrl-C in ``vslam run``, through
``stop_on_interrupt``) or, in the pipeline, ``dataset.max_frames``.

Frame times (seconds): a video file's container times (``CAP_PROP_POS_MSEC``); a device or URL, the monotonic
clock when its frame was grabbed; a RealSense, the device's frame timestamp.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from vslam.data.camera_file import CAMERA_FILE_NAME, read_camera_file
from vslam.data.types import Calibration, Frame, PinholeCamera, Sequence
from vslam.errors import ConfigError, DatasetError

logger = logging.getLogger(__name__)

URL_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "tcp://", "srt://")


def _error(source: str, reason: str) -> DatasetError:
    """A DatasetError naming ``source`` as given (DatasetError makes it a Path, which would fold a URL's //)."""
    e = DatasetError(source, reason)
    e.args = (f"{source}: {reason}",)
    return e


@dataclass(frozen=True)
class LiveConfig:
    """``dataset.live``: how a live source is read."""

    queue: int = 2  # frames held for the tracker; when full, the oldest is dropped
    # a video file given as the live source: replayed at its frame rate (the grabber sleeps to the container
    # times, so a slow tracker sees drops as with a camera); false: as fast as it decodes (tests)
    realtime: bool = True
    # capture mode asked of a device or RealSense (0: the camera's default; RealSense: 640x480 at 30 Hz)
    width: int = 0
    height: int = 0
    fps: float = 0.0
    timeout: float = 5.0  # seconds without a frame from a device or stream before it counts as ended

    def __post_init__(self) -> None:
        if self.queue < 1:
            raise ConfigError(f"dataset.live.queue must be at least 1 frame, got {self.queue}")
        if not self.timeout > 0:
            raise ConfigError(f"dataset.live.timeout must be positive seconds, got {self.timeout}")


class FrameQueue:
    """Holds at most ``size`` items; ``put`` never blocks: when full, the oldest item is dropped (``dropped``
    counts them). ``close`` ends it: ``get`` returns the items left, then None."""

    def __init__(self, size: int):
        self._items: collections.deque = collections.deque()
        self._size = size
        self._cond = threading.Condition()
        self._closed = False
        self._error: BaseException | None = None
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._cond:
            if len(self._items) >= self._size:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def close(self, error: BaseException | None = None) -> None:
        with self._cond:
            self._closed = True
            self._error = error
            self._cond.notify_all()

    def get(self, stop: threading.Event, poll: float = 0.05) -> Any:
        """The oldest item; None once closed and empty, or as soon as ``stop`` is set. The grabber's error, if
        it ended on one, is raised instead (frames before it were delivered)."""
        with self._cond:
            while not self._items and not self._closed and not stop.is_set():
                self._cond.wait(poll)
            if stop.is_set():
                return None
            if self._items:
                return self._items.popleft()
            if self._error is not None:
                raise self._error
            return None


# ------------------------------------------------------------------------------ sources
# A source: ``read() -> (timestamp s, image (H,W,3) uint8 BGR, depth (H,W) float32 metres or None) or None``
# at the end of the stream; ``release()``; ``size`` (width, height); ``calibration(camera file, sensor)``.


def _quiet_opencv():
    """OpenCV's own warnings (a device index that does not exist) silenced: the DatasetError says it in one line."""
    logging_mod = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging_mod is None:
        return contextlib.nullcontext()

    @contextlib.contextmanager
    def quiet():
        before = logging_mod.getLogLevel()
        logging_mod.setLogLevel(logging_mod.LOG_LEVEL_ERROR)
        try:
            yield
        finally:
            logging_mod.setLogLevel(before)

    return quiet()


class _OpenCVSource:
    """A device index, a stream URL or a video file through cv2.VideoCapture."""

    def __init__(self, source: str, kind: str, cfg: LiveConfig):
        self.source, self.kind, self.cfg = source, kind, cfg
        with _quiet_opencv():
            if kind == "device":
                cap = cv2.VideoCapture(int(source))
            elif kind == "url":
                timeouts = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(cfg.timeout * 1e3),
                            cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(cfg.timeout * 1e3)]
                cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG, timeouts)
            else:
                cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG)
        if not cap.isOpened():
            what = {"device": f"no camera at device index {source}", "url": "the stream cannot be opened",
                    "file": "unreadable video: OpenCV (FFmpeg) cannot open it"}[kind]
            raise _error(source, f"{what} (live input: a device index, a stream URL or a video file)")
        if kind == "device":
            for prop, v in ((cv2.CAP_PROP_FRAME_WIDTH, cfg.width), (cv2.CAP_PROP_FRAME_HEIGHT, cfg.height),
                            (cv2.CAP_PROP_FPS, cfg.fps)):
                if v:
                    cap.set(prop, v)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the driver's own queue: as short as it allows (V4L2)
        self.cap = cap
        self.fps = cap.get(cv2.CAP_PROP_FPS)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self._first: tuple[float, np.ndarray, None] | None = None
        if w <= 0 or h <= 0:  # a stream that states no size: its first frame does
            self._first = self.read()
            if self._first is None:
                self.release()
                raise _error(source, "opened but gave no frame (live input)")
            h, w = self._first[1].shape[:2]
        self.size = (w, h)
        self._n = 0
        self._t_prev = -np.inf
        self._t0: tuple[float, float] | None = None  # (monotonic, container time) of the first frame replayed

    def calibration(self, camera: Path, sensor: str) -> Calibration:
        return read_camera_file(camera).calibration(*self.size, sensor)

    def read(self) -> tuple[float, np.ndarray, None] | None:
        if self._first is not None:
            first, self._first = self._first, None
            return first
        deadline = time.monotonic() + self.cfg.timeout
        while True:
            ok = self.cap.grab()
            t_grab = time.monotonic()
            if ok:
                ok, image = self.cap.retrieve()
                if ok and image is not None:
                    break
            if self.kind == "file" or time.monotonic() > deadline:
                if self.kind != "file":
                    logger.warning("%s: no frame for %.1f s (dataset.live.timeout): the stream has ended",
                                   self.source, self.cfg.timeout)
                return None
            time.sleep(0.01)
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if self.kind != "file":
            t = t_grab
        else:  # the container's time; frame index / rate where the container's times do not increase
            t = self.cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3
            if not t > self._t_prev:
                t = self._n / self.fps if self.fps > 0 else t_grab
            if self.cfg.realtime:
                if self._t0 is None:
                    self._t0 = (time.monotonic(), t)
                due = self._t0[0] + (t - self._t0[1])
                time.sleep(max(0.0, due - time.monotonic()))
        self._n += 1
        self._t_prev = t
        return t, image, None

    def release(self) -> None:
        self.cap.release()


class _RealSenseSource:
    """Colour (BGR) and, for an RGB-D run, depth aligned to the colour camera, through ``pyrealsense2``.

    Not exercised by the tests (no camera here); written from the pyrealsense2 API."""

    def __init__(self, source: str, serial: str, sensor: str, cfg: LiveConfig):
        try:
            import pyrealsense2 as rs
        except ImportError:
            raise _error(source, "an Intel RealSense needs the optional 'realsense' extra: "
                                       "pip install 'vslam[realsense]' (pyrealsense2)") from None
        self.source, self.cfg = source, cfg
        w, h, fps = cfg.width or 640, cfg.height or 480, int(cfg.fps or 30)
        conf = rs.config()
        if serial:
            conf.enable_device(serial)
        conf.enable_stream(rs.stream.color, w, h, rs.format.bgr8, fps)
        self.rgbd = sensor == "rgbd"
        if self.rgbd:
            conf.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
        self.pipe = rs.pipeline()
        try:
            profile = self.pipe.start(conf)
        except RuntimeError as e:
            raise _error(source, f"RealSense {serial or '(first found)'} cannot stream {w}x{h} at {fps} Hz: "
                                       f"{e}") from None
        self.depth_units = profile.get_device().first_depth_sensor().get_depth_scale() if self.rgbd else 0.0  # m/unit
        self.align = rs.align(rs.stream.color) if self.rgbd else None
        intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        coeffs = tuple(float(c) for c in intr.coeffs)
        model = "none"
        if any(coeffs):
            if intr.model in (rs.distortion.brown_conrady, rs.distortion.modified_brown_conrady):
                model = "radtan"  # (k1, k2, p1, p2, k3), OpenCV's order
            else:
                logger.warning("%s: colour distortion model %s not supported; ignored (give --camera to override)",
                               source, intr.model)
        self.camera = PinholeCamera(intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy, model,
                                    coeffs[:5] if model == "radtan" else ())
        self.size = (intr.width, intr.height)
        self._t_prev = -np.inf

    def calibration(self, camera: Path | None, sensor: str) -> Calibration:
        scale = 1.0 / self.depth_units if self.rgbd else None
        if camera is not None:  # a camera file overrides the factory intrinsics
            cal = read_camera_file(camera).calibration(*self.size, sensor)
            return Calibration(cam0=cal.cam0, T_body_cam0=cal.T_body_cam0, imu=cal.imu, depth_scale=scale)
        from vslam.data.calibration import check_calibration

        return check_calibration(Calibration(cam0=self.camera, depth_scale=scale), "RealSense factory calibration",
                                 {f: (f"colour {f}", None) for f in ("fx", "fy", "cx", "cy", "width", "height")})

    def read(self) -> tuple[float, np.ndarray, np.ndarray | None] | None:
        while True:
            try:
                frames = self.pipe.wait_for_frames(int(self.cfg.timeout * 1e3))
            except RuntimeError as e:  # no frame within the timeout: unplugged or stalled
                logger.warning("%s: %s: the stream has ended", self.source, e)
                return None
            if self.align is not None:
                frames = self.align.process(frames)
            color = frames.get_color_frame()
            depth = frames.get_depth_frame() if self.rgbd else None
            if not color or (self.rgbd and not depth):
                continue
            t = color.get_timestamp() / 1e3  # ms -> s (device clock, or host-synchronised global time)
            if not t > self._t_prev:
                continue
            self._t_prev = t
            image = np.asanyarray(color.get_data()).copy()
            d = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_units) if depth else None
            return t, image, d

    def release(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.pipe.stop()


def source_kind(source: str) -> str:
    """"device", "url", "realsense" or "file" for a live source string; DatasetError when it is none of them."""
    s = source.strip()
    if s.isdigit():
        return "device"
    if s.lower().startswith(URL_SCHEMES):
        return "url"
    if s.lower() == "realsense" or s.lower().startswith("realsense:"):
        return "realsense"
    if Path(s).expanduser().is_file():
        return "file"
    raise _error(source, "not a live source: expected a camera device index (0, 1, ...), a stream URL "
                               "(rtsp://, http://, ...), realsense[:SERIAL] or a video file")


# ------------------------------------------------------------------------------ the sequence


class LiveSequence(Sequence):
    """Frames from a live ``source`` (see ``source_kind``), newest first when the tracker falls behind.

    Intrinsics from ``camera`` (camera.yaml or ORB-SLAM3 settings, docs/inputs.md); default: a video file's
    ``<stem>.yaml`` or camera.yaml beside it, camera.yaml in the working folder for a device or URL, the
    device's factory calibration for a RealSense. Frames: image (H,W,3) uint8 BGR; depth (H,W) float32
    metres for a RealSense RGB-D run; no ground truth. ``len()`` is a TypeError: the length is unknown.
    """

    live = True

    def __init__(self, path: str | int | Path, camera: str | Path | None = None, sensor: str = "mono",
                 config: LiveConfig = LiveConfig()):
        self.source = str(path).strip()
        self.kind = source_kind(self.source)
        rgbd_ok = self.kind == "realsense"
        if sensor not in (("mono", "rgbd") if rgbd_ok else ("mono",)):
            raise _error(self.source, f"sensor {sensor!r} not available from this live source "
                                            f"({'colour + depth' if rgbd_ok else 'one colour view, no depth'}); "
                                            f"use --sensor {'rgbd or ' if rgbd_ok else ''}mono")
        self.sensor = sensor  # type: ignore[assignment]
        self.config = config
        self.camera_path = Path(camera).expanduser() if camera else self._default_camera()
        if self.kind == "file":
            self.name = Path(self.source).stem
        elif self.kind == "device":
            self.name = f"camera{self.source}"
        else:
            self.name = self.source.split("://")[-1].replace("/", "_").replace(":", "_") or "live"
        self._src: Any = self._open()  # opened now: a camera that is not there is an error at open time
        try:
            self.calibration = self._src.calibration(self.camera_path, sensor)
        except BaseException:
            self._src.release()
            raise
        self._stop = threading.Event()
        self._times: list[float] = []
        self.dropped = 0  # frames the queue dropped over the last iteration
        self._grabber: threading.Thread | None = None  # the running iteration's grabber thread
        self._done: threading.Event | None = None  # set: that grabber stops after the read in progress

    def _default_camera(self) -> Path | None:
        if self.kind == "realsense":
            return None
        if self.kind == "file":
            p = Path(self.source).expanduser()
            return next((c for c in (p.with_suffix(".yaml"), p.parent / CAMERA_FILE_NAME) if c.is_file()),
                        p.parent / CAMERA_FILE_NAME)
        return Path(CAMERA_FILE_NAME)

    def _open(self) -> Any:
        if self.kind == "realsense":
            return _RealSenseSource(self.source, self.source.partition(":")[2], self.sensor, self.config)
        return _OpenCVSource(str(Path(self.source).expanduser()) if self.kind == "file" else self.source,
                             self.kind, self.config)

    def __getstate__(self) -> dict[str, Any]:
        raise TypeError("a live source cannot be sent to another process")

    def __len__(self) -> int:
        raise TypeError("a live source has no length: frames come until the stream ends, Ctrl-C or max_frames")

    def timestamps(self) -> np.ndarray:
        """(N,) float64 seconds of the frames delivered so far."""
        return np.asarray(self._times, np.float64)

    def close(self) -> None:
        """Stop the grabber thread of an iteration in progress and release the device, stream or file, also
        when the sequence was never iterated (its source is opened by ``__init__``). Iterating again opens the
        source again. (From another thread during an iteration: the consumer then gets the frames already
        queued, then the end of the stream.)"""
        if self._done is not None:
            self._done.set()
        grabber = self._grabber
        if grabber is not None and grabber is not threading.current_thread():
            grabber.join(timeout=self.config.timeout + 1.0)  # it releases its source on the way out
        src, self._src = self._src, None
        if src is not None:
            src.release()

    def stop(self) -> None:
        """End the iteration: the frame being delivered is the last one (thread-safe; a signal handler's)."""
        self._stop.set()

    @contextlib.contextmanager
    def stop_on_interrupt(self) -> Iterator[None]:
        """Within it, Ctrl-C ends the stream (the run finishes with the frames so far); a second Ctrl-C
        interrupts as usual. Does nothing outside the main thread."""
        self._stop.clear()
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def on_sigint(signum: int, frame: Any) -> None:
            if self._stop.is_set():
                raise KeyboardInterrupt
            logger.warning("Ctrl-C: live input stopped; finishing the run with the frames so far "
                           "(Ctrl-C again to abort)")
            self._stop.set()

        previous = signal.signal(signal.SIGINT, on_sigint)
        try:
            yield
        finally:
            signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)

    def _grab(self, src: Any, q: FrameQueue, done: threading.Event) -> None:
        """The grabber thread: every frame the source gives, numbered and stamped, into ``q``, until the stream
        ends, ``stop()`` or the consumer is ``done``."""
        index = 0
        try:
            while not (self._stop.is_set() or done.is_set()):
                got = src.read()
                if got is None:
                    break
                t, image, depth = got
                q.put(Frame(index=index, timestamp=float(t), image=image, depth=depth))
                index += 1
            q.close()
        except BaseException as e:  # raised in the consumer's thread
            q.close(e)
        finally:
            src.release()

    def __iter__(self) -> Iterator[Frame]:
        src, self._src = self._src, None
        if src is None:  # a second iteration: the source again, from its current frame
            src = self._open()
        q = FrameQueue(self.config.queue)
        self._times = []
        done = threading.Event()
        grabber = threading.Thread(target=self._grab, args=(src, q, done), name="vslam-live-grab", daemon=True)
        self._grabber, self._done = grabber, done
        grabber.start()
        try:
            while True:
                frame = q.get(self._stop)
                if frame is None:
                    return
                self._times.append(frame.timestamp)
                yield frame
        finally:
            done.set()
            grabber.join(timeout=self.config.timeout + 1.0)  # a read in progress ends within the source's timeout
            if self._grabber is grabber:
                self._grabber = self._done = None
            self.dropped = q.dropped
            if q.dropped:
                logger.info("%s: %d frames dropped by the live queue (%d delivered)", self.source, q.dropped,
                            len(self._times))
