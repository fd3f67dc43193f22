"""Child Python processes that talk length-prefixed pickles over their stdin / stdout.

Used by the local BA worker (``vslam.backend.worker``) and the front-end process
(``vslam.tracking.frontend_process``): GTSAM's binding holds the GIL while it optimises, so work that must overlap
it needs a process, not a thread. The children are ``python -m <module>``, not ``multiprocessing`` ones: a
spawned child re-imports the caller's ``__main__`` (which breaks a user script without an ``if __name__ ==
"__main__"`` guard), and a forked one inherits the parent's threads (OpenCV's pool, torch, the prefetcher) with
whatever locks they held.
"""

from __future__ import annotations

import os
import pickle
import resource
import struct
import subprocess
import sys
from pathlib import Path
from typing import BinaryIO

_HEADER = struct.Struct("<Q")


def send(f: BinaryIO, obj: object) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_HEADER.pack(len(data)))
    f.write(data)
    f.flush()


def receive(f: BinaryIO) -> object:
    """The next object; EOFError when the other side closed the stream (or died mid-message)."""
    head = f.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError
    (n,) = _HEADER.unpack(head)
    data = f.read(n)
    if len(data) < n:
        raise EOFError
    return pickle.loads(data)


def spawn(module: str, blas_threads: int | None = None) -> subprocess.Popen:
    """``python -m module`` with pipes on stdin / stdout (stderr shared with this process), this checkout's
    package importable, and numpy's BLAS threads ``blas_threads`` (None: as this process has them now --
    ``RuntimeConfig.blas_threads`` while a run lasts; 0: the library's default)."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])  # the folder holding the vslam package
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    if blas_threads is None:
        from threadpoolctl import threadpool_info

        blas = [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]
        blas_threads = min(blas) if blas else 0
    if blas_threads > 0:
        env["OPENBLAS_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(blas_threads)
    # A session of its own: Ctrl-C in the terminal reaches this process only, which ends the child in order
    # (``stop``) instead of the child dying mid-message with a KeyboardInterrupt traceback of its own.
    return subprocess.Popen([sys.executable, "-m", module], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                            start_new_session=True)


def result_stream() -> BinaryIO:
    """In a child: the stream its results go to (the original stdout); fd 1 then points at stderr, so that
    anything a library prints cannot corrupt the result stream."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    return out


def stop(proc: subprocess.Popen | None, timeout: float = 10.0) -> None:
    """Close the child's input (EOF: its loop ends), wait for it, kill it if it does not end."""
    if proc is None:
        return
    try:
        proc.stdin.close()  # type: ignore[union-attr]
        proc.wait(timeout=timeout)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
    proc.stdout.close()  # type: ignore[union-attr]


def peak_rss_mb() -> float:
    """Peak resident memory of this process plus that of its largest finished child (the front-end process,
    the BA worker): an upper bound of what a run held at once, MB (Linux reports KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return (own + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0


def usable_cpus() -> int:
    """The CPUs this process may run on (containers, taskset restrict them), else the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
