"""Frames into the tracker: read ahead on a thread (``prefetch``) or made with their front end in a child process
(``frontend_process``), and which frames the reader skipped."""

from __future__ import annotations

import logging
import pickle
import queue
import threading
from typing import TYPE_CHECKING, Any, Callable, Iterator

import numpy as np

from vslam.data.types import Frame, Sequence
from vslam.pipeline.runtime import torch_thread_count

if TYPE_CHECKING:
    from vslam.pipeline.config import PipelineConfig

log = logging.getLogger(__name__)


def prefetch(seq: Sequence, n: int, depth: int = 3,
             prepare: Callable[[Frame], Any] | None = None) -> Iterator[tuple[Frame, Any]]:
    """The first ``n`` frames of ``seq`` as (frame, prepare(frame) or None), made on a background thread while
    the caller tracks.

    PNG decoding and ``prepare`` (the tracker's image-only front end: OpenCV and torch release the GIL) then
    overlap tracking on a second core; the order and content of the frames are unchanged, and an exception
    in the reader or in ``prepare`` is re-raised here.
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce() -> None:
        try:
            for k, frame in enumerate(seq):
                if k >= n or stop.is_set():
                    break
                q.put((frame, prepare(frame) if prepare is not None else None))
            q.put(done)
        except BaseException as e:  # handed to the consumer, raised in its thread
            q.put(e)

    worker = threading.Thread(target=produce, name="vslam-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while worker.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                worker.join(0.01)


def frontend_process(seq: Sequence, n: int, cfg: PipelineConfig):
    """A ``FrontEndProcess`` for the run (``RuntimeConfig.frontend_process``), or None -- the prefetch thread
    then -- when the sequence cannot be sent to a child process or no child can be started."""
    from vslam.tracking.frontend_process import FrontEndProcess

    try:
        return FrontEndProcess(seq, n, seq.calibration, cfg.dataset.sensor, cfg.slam, cfg.runtime,
                               torch_threads=torch_thread_count(cfg.runtime), blas_threads=cfg.runtime.blas_threads)
    except (TypeError, AttributeError, pickle.PicklingError, OSError) as e:
        log.info("front end on a thread: the sequence cannot be sent to a child process, or none started (%s)", e)
        return None


def skipped_frames(seq: Sequence, received: list[int], n_total: int) -> list[int]:
    """Indices of the frames the run should have read but the reader skipped (they did not decode): the holes in
    the indices received, and the missing tail when the reading stopped early. Taken from the indices, not from
    the reader's ``skipped`` list: a front-end process reads (and skips) in a child, whose list is not ours, and a
    video lists its lost frames for the whole file, also past where the run stopped."""
    expected = np.asarray(getattr(seq, "indices", np.arange(len(seq))), np.int64)
    got = set(received)
    last = max(received) if received else -1
    holes = {int(i) for i in expected[expected <= last] if int(i) not in got}
    missing = n_total - len(received) - len(holes)
    if missing > 0:  # the reading stopped before the frames it was asked for: the rest did not decode
        holes |= set(expected[expected > last][:missing].tolist())
    return sorted(holes)
