"""Local BA in a second process, so that it overlaps the tracking of the next frames.

GTSAM's Python binding holds the GIL while it optimises (measured: a Python loop in another thread stalls for
the whole solve), so a thread cannot overlap tracking with BA; a process can. ORB-SLAM runs local mapping in
its own thread and tracks against whatever the map is at that moment; here the caller decides on a fixed
frame schedule when a result is applied (``MappingConfig.ba_lag_frames``), so runs stay deterministic: the
worker computes exactly what ``local_bundle_adjustment`` computes in-process (same code, same inputs).

The worker is ``python -m vslam.backend.worker`` talking pickles over its stdin/stdout, not a
``multiprocessing`` child: a spawned child re-imports the caller's ``__main__``, which breaks any user script
without an ``if __name__ == "__main__"`` guard, and a forked one inherits the parent's threads (OpenCV, torch,
the frame prefetcher).
"""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import sys
from pathlib import Path
from typing import BinaryIO

from vslam.backend.ba import BackendConfig, BAProblem, BAResult, StereoCamera, local_bundle_adjustment

_HEADER = struct.Struct("<Q")


def _send(f: BinaryIO, obj: object) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_HEADER.pack(len(data)))
    f.write(data)
    f.flush()


def _receive(f: BinaryIO) -> object:
    head = f.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError
    (n,) = _HEADER.unpack(head)
    return pickle.loads(f.read(n))


class BAWorker:
    """One child process that solves local BA problems in submission order; started on first use."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._waiting = 0

    def start(self) -> None:
        """Start the process now (it imports GTSAM for ~0.3 s while the caller reads its first frames)."""
        if self._proc is None or self._proc.poll() is not None:
            env = dict(os.environ)
            root = str(Path(__file__).resolve().parents[2])  # the folder holding the vslam package
            env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
            from threadpoolctl import threadpool_info

            # numpy's BLAS threads as the parent has them now (``SlamConfig.blas_threads`` while a run lasts)
            blas = [i["num_threads"] for i in threadpool_info() if i.get("user_api") == "blas"]
            if blas:
                env["OPENBLAS_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(min(blas))
            self._proc = subprocess.Popen([sys.executable, "-m", "vslam.backend.worker"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, env=env)
            self._waiting = 0

    def submit(self, problem: BAProblem, camera: StereoCamera, cfg: BackendConfig) -> None:
        self.start()
        _send(self._proc.stdin, (problem, camera, cfg))  # type: ignore[union-attr,arg-type]
        self._waiting += 1

    def result(self) -> BAResult:
        """The oldest submitted problem's result (blocks until the worker has it)."""
        if self._proc is None or self._waiting == 0:
            raise RuntimeError("BAWorker.result: nothing was submitted")
        try:
            status, payload = _receive(self._proc.stdout)  # type: ignore[arg-type,misc]
        except EOFError:
            raise RuntimeError(f"the local BA worker process died (exit code {self._proc.wait()})") from None
        self._waiting -= 1
        if status != "ok":
            raise RuntimeError(f"local BA failed in the worker process: {payload}")
        return payload  # type: ignore[return-value]

    def close(self) -> None:
        if self._proc is not None:
            try:
                self._proc.stdin.close()  # type: ignore[union-attr]  # EOF: the worker's loop ends
                self._proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
            self._proc.stdout.close()  # type: ignore[union-attr]
            self._proc = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the child sees EOF and exits on its own
            pass


def _serve() -> None:
    """The worker's loop: (problem, camera, cfg) in on stdin -> ("ok", BAResult) | ("error", text) out."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # anything the solver prints goes to stderr, not into the result stream
    inp = sys.stdin.buffer
    while True:
        try:
            problem, camera, cfg = _receive(inp)  # type: ignore[misc]
        except EOFError:
            return
        try:
            reply: tuple[str, object] = ("ok", local_bundle_adjustment(problem, camera, cfg))
        except Exception as e:  # the parent raises it where it waits
            reply = ("error", f"{type(e).__name__}: {e}")
        _send(out, reply)


if __name__ == "__main__":
    _serve()
