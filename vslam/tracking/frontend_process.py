"""The image-only front end -- decoding the frames and ``SlamTracker.frontend`` (keypoints, segments, keypoint
depth, detector boxes) -- in a child process, up to ``ahead`` frames ahead of tracking.

Why not only the prefetch thread (``RuntimeConfig.frontend_thread``): on TUM teddy (2 cores) the tracking thread
is quick on a frame and slow on a keyframe (local BA), the front end (PNG decode + ORB) costs the same on every
frame; the two balance over a keyframe's frames -- if the front end could work ahead through each BA. A thread
cannot: GTSAM's optimiser holds the GIL through each LM round, and the thread's queue was short. Each frame after
a BA then waited for the front end (stats.csv ms_decode; the timings in docs/speed.md). A process has its own GIL.

How the frames travel: a TUM frame pickles to ~2.2 MB (colour + float depth), which through a pipe needs the
reader's GIL dozens of times per frame -- a reader thread beside GTSAM starved, and the child blocked on the
full pipe. So each frame is a file in a private folder on a RAM file system (``/dev/shm`` where there is one),
the pipe carries only "frame k is ready", and the tracking thread reads the file when it wants the frame. The
child stays at most ``ahead`` frames ahead: after that it waits for one acknowledgement byte per frame read.

The child builds its own ``SlamTracker`` from the same calibration, sensor and config (loop closing, IMU,
saved maps and the BA worker off: the front end uses none of them) and runs the same ``frontend`` code on the
same frames, so the numbers are those of the thread, bit for bit; it reads the sequence itself (the sequence
is pickled to it). Its log records (a frame that does not decode) go to this process's loggers.

Inside the child the sequence is read (decoded, rendered) on one thread and the front ends are made on
``RuntimeConfig.frontend_workers`` others, each with a tracker of its own; the frames go out in order. Why: on EuRoC
stereo (2 cores) the front end (two PNGs, two ORB passes, the stereo match) takes several times what tracking
takes a frame (docs/speed.md), so one core idled while tracking waited; the front end of a frame depends on its
images alone, so two frames can be made at once (OpenCV and numpy release the GIL) with the same numbers.
"""

from __future__ import annotations

import logging
import mmap
import os
import pickle
import queue
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

from vslam import childproc
from vslam.data.types import Calibration, Frame, Sequence, SensorKind
from vslam.errors import VslamError
from vslam.runtime import RuntimeConfig

if TYPE_CHECKING:
    from vslam.tracking.slam import SlamConfig


class FrontEndProcess:
    """``for frame, front in FrontEndProcess(seq, n, ...)``: the first ``n`` frames of ``seq`` with their
    ``SlamTracker.frontend``, made by a child process. An error in the child (a frame that does not decode, a
    missing checkpoint) is raised here, with its message. Raises TypeError / pickle.PicklingError / AttributeError
    at once when the sequence cannot be sent to a child (a user's own Sequence class holding an open handle): use
    the thread then. ``close()`` (or the end of the iteration) stops the child and removes its folder."""

    def __init__(self, seq: Sequence, n: int, calibration: Calibration, sensor: SensorKind, cfg,
                 runtime: RuntimeConfig = RuntimeConfig(), torch_threads: int = 0, blas_threads: int | None = None,
                 ahead: int = 8):
        self._proc: subprocess.Popen | None = None
        ram = _ram_dir()
        remove_stale_folders(Path(ram or tempfile.gettempdir()))
        self._dir = Path(tempfile.mkdtemp(prefix=f"{_PREFIX}{os.getpid()}-", dir=ram))
        try:  # the spec goes through a file: the pipe would hold this thread until the child has imported
            with open(self._dir / "spec.pkl", "wb") as f:
                pickle.dump((seq, n, calibration, sensor, cfg, runtime, torch_threads, ahead,
                             logging.getLogger("vslam").getEffectiveLevel()), f, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc = childproc.spawn("vslam.tracking.frontend_process", blas_threads)
        except BaseException:  # no child: the folder goes now, not with a later run's stale-folder sweep
            shutil.rmtree(self._dir, ignore_errors=True)
            raise
        childproc.send(self._proc.stdin, str(self._dir))  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[tuple[Frame, object]]:
        try:
            while self._proc is not None:
                try:
                    msg = childproc.receive(self._proc.stdout)  # type: ignore[arg-type]
                except EOFError:
                    raise RuntimeError(f"the front-end process died (exit code {self._proc.wait()})") from None
                if msg[0] == "done":  # type: ignore[index]
                    return
                if msg[0] == "error":  # type: ignore[index]
                    raise msg[1]  # type: ignore[index,misc]
                if msg[0] == "log":  # type: ignore[index]
                    record = logging.makeLogRecord(msg[1])  # type: ignore[index]
                    logging.getLogger(record.name).handle(record)
                    continue
                path = self._dir / f"{msg[1]}.pkl"  # type: ignore[index]
                item = read_frame_file(path)
                path.unlink()  # its memory stays mapped while the frame's arrays live
                try:
                    self._proc.stdin.write(b"\x01")  # type: ignore[union-attr]  # one more frame may be made
                    self._proc.stdin.flush()  # type: ignore[union-attr]
                except BrokenPipeError:  # the child has finished (or failed: its message follows)
                    pass
                yield item  # type: ignore[misc]
        finally:
            self.close()

    def close(self) -> None:
        """Stop the child now (it may be waiting to make frames nobody will read) and remove its folder."""
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
            for f in (self._proc.stdin, self._proc.stdout):
                try:
                    f.close()  # type: ignore[union-attr]
                except OSError:
                    pass
            self._proc = None
        shutil.rmtree(self._dir, ignore_errors=True)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass


_LEN = struct.Struct("<Q")
# Arrays from this many bytes up are mapped from the frame file, each with a mapping of its own: one kept
# (a keyframe's descriptors) then keeps its own pages, not the frame's image and depth as views into one
# mapping of the whole file would (a long run would hold every keyframe's frame file). Smaller ones
# (keypoints, ORB descriptors) are copied: cheap, and no mapping per array.
_MAP_MIN = 1 << 16


def _aligned(pos: int, n: int) -> int:
    """Where a buffer of ``n`` bytes starts at or after ``pos``: a page boundary (mmap offsets must be one) when it
    is mapped, else 64 bytes."""
    a = mmap.ALLOCATIONGRANULARITY if n >= _MAP_MIN else 64
    return pos + (-pos % a)


def write_frame_file(path: Path, obj: object) -> None:
    """``obj`` as a pickle whose arrays are stored apart, aligned (protocol 5 out-of-band buffers):
    ``read_frame_file`` maps the large ones instead of copying ~2 MB per frame."""
    buffers: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    raws = [b.raw() for b in buffers]
    with open(path, "wb") as f:
        f.write(_LEN.pack(len(raws)) + _LEN.pack(len(head)) + b"".join(_LEN.pack(r.nbytes) for r in raws) + head)
        for r in raws:
            f.write(b"\0" * (_aligned(f.tell(), r.nbytes) - f.tell()))
            f.write(r)


def read_frame_file(path: Path) -> object:
    """The object ``write_frame_file`` stored. Its arrays are writable: the large ones copy-on-write views of
    their own mapping of the file (the file itself never changes), alive as long as they are; the small ones
    copies."""
    buffers: list[memoryview | bytearray] = []
    with open(path, "rb") as f:
        (nbuf,), (nhead,) = _LEN.unpack(f.read(8)), _LEN.unpack(f.read(8))
        sizes = [_LEN.unpack(f.read(8))[0] for _ in range(nbuf)]
        head = f.read(nhead)
        pos = 16 + 8 * nbuf + nhead
        for n in sizes:
            pos = _aligned(pos, n)
            if n >= _MAP_MIN:
                buffers.append(memoryview(mmap.mmap(f.fileno(), n, access=mmap.ACCESS_COPY, offset=pos)))
            else:
                buf = bytearray(n)
                f.seek(pos)
                f.readinto(buf)
                buffers.append(buf)
            pos += n
    return pickle.loads(head, buffers=buffers)


_PREFIX = "vslam-frontend-"  # + the tracking process's pid: whose frame files a folder holds


def remove_stale_folders(root: Path) -> list[Path]:
    """Remove frame-file folders left in ``root`` by runs whose process no longer exists (killed before it could
    clean up: up to ``ahead`` frames, ~18 MB of RAM on TUM). -> the folders removed."""
    gone = []
    for d in root.glob(f"{_PREFIX}*-*"):
        pid = d.name[len(_PREFIX):].split("-", 1)[0]
        if not pid.isdigit() or not d.is_dir():
            continue
        try:
            os.kill(int(pid), 0)  # signal 0: does the process exist?
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
            gone.append(d)
        except OSError:  # exists, owned by someone else
            pass
    return gone


def _ram_dir(min_free: int = 256 << 20) -> str | None:
    """A folder on a RAM file system for the frame files, None (the default temp folder) if there is none or it
    has less than ``min_free`` bytes free (a container's /dev/shm is often 64 MB: 8 frames of 1280x720 RGB-D
    nearly fill it)."""
    try:
        ok = os.access("/dev/shm", os.W_OK) and shutil.disk_usage("/dev/shm").free >= min_free
    except OSError:
        ok = False
    return "/dev/shm" if ok else None


def frontend_only(cfg):
    """``cfg`` with what the front end does not use switched off (no loop database, IMU, map file or BA
    worker is built in the child)."""
    return replace(cfg, loop=replace(cfg.loop, enabled=False), load_map="", save_map=False,
                   inertial=replace(cfg.inertial, enabled=False), mapping=replace(cfg.mapping, ba_lag_frames=0))


def _portable(e: Exception) -> Exception:
    """``e`` if it survives a pickle round trip as itself, else the same message in a type that does (a
    VslamError stays a VslamError: the CLI prints those as one line)."""
    try:
        back = pickle.loads(pickle.dumps(e))
        if type(back) is type(e) and str(back) == str(e):
            return e
    except Exception:
        pass
    return VslamError(str(e)) if isinstance(e, VslamError) else RuntimeError(f"{type(e).__name__}: {e}")


class _ForwardLogs(logging.Handler):
    """Sends the child's log records to the parent, which hands them to its own loggers: the same format, level
    and handlers as a message logged there (a frame that does not decode, for instance)."""

    def __init__(self, send) -> None:
        super().__init__()
        self._send = send

    def emit(self, record: logging.LogRecord) -> None:
        self._send(("log", {"name": record.name, "levelno": record.levelno, "levelname": record.levelname,
                            "msg": record.getMessage(), "pathname": record.pathname, "lineno": record.lineno,
                            "funcName": record.funcName, "created": record.created}))


def frame_workers(cfg: SlamConfig, runtime: RuntimeConfig, sensor: SensorKind, ahead: int) -> int:
    """How many frames the child makes at once: ``RuntimeConfig.frontend_workers``, or for 0 two for stereo without a
    network when the process may use two CPUs, else one. Stereo: two ORB passes and the stereo match make the
    front end heavier than tracking (EuRoC); an RGB-D or monocular one keeps ahead alone (TUM; timings in
    docs/speed.md), and a network already spreads over the cores with torch's threads. Never more than ``ahead``, the
    frames the child may hold."""
    n = runtime.frontend_workers
    if n <= 0:
        network = cfg.features.extractor != "orb" or (cfg.dynamic.enabled and cfg.dynamic.source == "detector")
        n = 2 if sensor == "stereo" and not network and childproc.usable_cpus() >= 2 else 1
    return max(1, min(n, ahead))


def one_at_a_time(seq: Sequence, n: int, tracker, ahead: int,
                  may_read: Callable[[], bool]) -> Iterator[tuple[Frame, object] | None]:
    """``ordered_frontends`` with one tracker, on the calling thread: reading and front end in turn, no threads
    (where one worker suffices, a reader thread beside it only competes with the frame being made)."""
    for k, frame in enumerate(seq):
        if k >= n:
            return
        if k >= ahead and not may_read():
            yield None
            return
        yield frame, tracker.frontend(frame)


_END = object()


def ordered_frontends(seq: Sequence, n: int, trackers: list, ahead: int,
                      may_read: Callable[[], bool]) -> Iterator[tuple[Frame, object] | None]:
    """(frame, tracker.frontend(frame)) of the first ``n`` frames of ``seq``, in order; ``len(trackers)`` frames
    are made at once, one per tracker, while one more thread reads the sequence. Before it reads frame k >= ahead
    it calls ``may_read()`` (the parent has taken frame k - ahead; False: it stopped, and None is yielded last), so
    at most ``ahead`` frames are in flight; and it reads a frame only while fewer than ``len(trackers) + 1`` are
    read and not yet yielded (a frame decodes faster than its front end is made: the others would wait in memory).
    An error in the reader or a front end is raised here in its frame's place, after the frames before it."""
    items: queue.Queue = queue.Queue()  # (frame, future) in frame order
    free: queue.Queue = queue.Queue()  # the trackers not in use: each one is used by one thread at a time
    for t in trackers:
        free.put(t)
    slots = threading.Semaphore(len(trackers) + 1)
    stop = threading.Event()

    def make(frame: Frame) -> object:
        tracker = free.get()
        try:
            return tracker.frontend(frame)
        finally:
            free.put(tracker)

    pool = ThreadPoolExecutor(len(trackers), thread_name_prefix="frontend")

    def read() -> None:
        try:
            frames = iter(seq)
            for k in range(n):
                slots.acquire()
                frame = None if stop.is_set() else next(frames, None)
                if frame is None:
                    break
                if k >= ahead and not may_read():
                    items.put(None)
                    return
                items.put((frame, pool.submit(make, frame)))
            items.put(_END)
        except BaseException as e:  # raised in order by the consumer
            items.put(e)

    reader = threading.Thread(target=read, name="frontend-reader", daemon=True)
    reader.start()
    try:
        while True:
            item = items.get()
            if item is _END:
                return
            if item is None or isinstance(item, BaseException):
                if item is not None:
                    raise item
                yield None
                return
            frame, fut = item
            yield frame, fut.result()
            slots.release()
    finally:
        stop.set()  # a reader blocked in may_read ends with the process (daemon thread)
        slots.release()
        pool.shutdown(wait=False, cancel_futures=True)


def _serve() -> None:
    out = childproc.result_stream()
    inp = sys.stdin.buffer
    lock = threading.Lock()  # the log handler may send from another thread (the lines pool)

    def send(msg: object) -> None:
        with lock:
            childproc.send(out, msg)

    try:
        folder = str(childproc.receive(inp))
        spec = Path(folder, "spec.pkl")
        with open(spec, "rb") as f:
            seq, n, calibration, sensor, cfg, runtime, torch_threads, ahead, log_level = pickle.load(f)
        spec.unlink()  # not kept in RAM for the whole run
        root = logging.getLogger()
        root.handlers[:] = [_ForwardLogs(send)]
        root.setLevel(log_level)
        try:
            from vslam.tracking.slam import SlamTracker

            fcfg = frontend_only(cfg)
            trackers = [SlamTracker(calibration, sensor, fcfg, runtime=runtime)
                        for _ in range(frame_workers(cfg, runtime, sensor, ahead))]
            torch = sys.modules.get("torch")
            if torch is not None and torch_threads > 0:
                torch.set_num_threads(torch_threads)
            # the parent has read frame k - ahead before frame k is read (EOF: it stopped)
            may_read = lambda: bool(inp.read(1))  # noqa: E731
            made = one_at_a_time(seq, n, trackers[0], ahead, may_read) if len(trackers) == 1 else \
                ordered_frontends(seq, n, trackers, ahead, may_read)
            for k, item in enumerate(made):
                if item is None:
                    return
                write_frame_file(Path(folder, f"{k}.pkl"), item)
                send(("frame", k))
            send(("done",))
        except Exception as e:  # raised in the parent where it waits for the next frame
            send(("error", _portable(e)))
    except (BrokenPipeError, KeyboardInterrupt, EOFError):  # the parent stopped reading / was interrupted
        pass


if __name__ == "__main__":
    _serve()
