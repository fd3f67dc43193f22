"""Progress bars of the long commands, on a terminal only.

The library reports progress through a callback ``progress(done, total)`` and never prints; the CLI turns it
into a bar here. The bar goes to stderr, and only when stderr is a terminal: a log file, a pipe or CI gets
nothing (``--quiet`` or ``VSLAM_PROGRESS=0`` turn it off on a terminal too). It stays on screen when the work
ends, with the count, the rate and the time taken.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Callable, TextIO

#: what a long library function takes to report its work: ``progress(done, total)`` (total 0: unknown)
Progress = Callable[[int, int], None]
OFF = ("0", "false", "no", "off")  # values of VSLAM_PROGRESS that turn the bar off


def bar_enabled(quiet: bool = False, stream: TextIO | None = None) -> bool:
    """A bar is shown: not --quiet, not VSLAM_PROGRESS=0, not a torchrun rank other than 0 (they share the
    terminal; rank 0 reports the steps), and ``stream`` (default stderr) is a terminal."""
    if quiet or os.environ.get("VSLAM_PROGRESS", "").strip().lower() in OFF or os.environ.get("RANK", "0") != "0":
        return False
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def _shape(stream: TextIO) -> dict[str, Any]:
    """tqdm's size arguments. A terminal that reports no size (0 x 0: a pseudo-terminal nobody sized, as
    ``script`` opens from a pipe, or ``docker exec -t``) made tqdm take -1 rows and hide the bar as
    off-screen: such a one gets 80 x 24; a sized one is followed as it is resized."""
    try:
        cols, rows = os.get_terminal_size(stream.fileno())
    except (AttributeError, ValueError, OSError):
        cols = rows = 0
    return {"dynamic_ncols": True} if cols > 0 and rows > 0 else {"ncols": 79, "nrows": 24}


class ProgressBar:
    """``bar(done, total)`` moves a tqdm bar (the library's progress callback); ``close`` leaves its last line.

    Shown from when it is made, so that the time includes the start (a network loading, the first frame); the
    total may come with the first update (the pipeline opens the sequence). Total 0 or None: unknown (a live
    camera), the bar counts without an ETA. Disabled: every call is a no-op and tqdm is not imported."""

    def __init__(self, desc: str, total: int | None = None, unit: str = "frame", enabled: bool = True,
                 stream: TextIO | None = None) -> None:
        self.desc, self.total, self.unit, self.enabled = desc, total, unit, enabled
        self.stream = stream
        self._bar: Any = None
        self._logs: contextlib.ExitStack | None = None
        self._started = False  # an update came: the bar then stays on screen when closed
        if enabled:
            self._open()

    def _open(self) -> None:
        from tqdm import tqdm
        from tqdm.contrib.logging import logging_redirect_tqdm

        file = self.stream if self.stream is not None else sys.stderr
        self._bar = tqdm(total=self.total or None, desc=self.desc, unit=self.unit, leave=True, file=file, **_shape(file))
        self._logs = contextlib.ExitStack()  # log lines (-v) print above the bar instead of through it
        self._logs.enter_context(logging_redirect_tqdm())

    def __call__(self, done: int, total: int | None = None) -> None:
        bar = self._bar
        if bar is None:  # disabled, or finished
            return
        if total and bar.total != total:
            bar.total = total
        if not self._started and done > 1:  # resumed part-way (a training from its checkpoint): not in the rate
            bar.initial = bar.n = bar.last_print_n = done - 1
        self._started = True
        bar.update(done - bar.n)  # throttled by tqdm (mininterval) and timed for the rate and ETA
        if bar.total and done >= bar.total:
            # closed now: the last line's time and rate are the work's, not those of what follows (a run's report)
            self.close()

    update = __call__

    def close(self) -> None:
        if self._bar is not None:
            self._bar.leave = self._started  # an error before any work: no empty bar left above its message
            self._bar.close()
        if self._logs is not None:
            self._logs.close()
        self._bar = self._logs = None

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def progress_bar(desc: str, total: int | None = None, unit: str = "frame", quiet: bool = False,
                 stream: TextIO | None = None) -> ProgressBar:
    """The bar of one long command: shown on a terminal (``bar_enabled``), a no-op otherwise."""
    return ProgressBar(desc, total, unit, bar_enabled(quiet, stream), stream)
