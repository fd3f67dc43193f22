"""Local BA in a second process, so that it overlaps the tracking of the next frames.

GTSAM's Python binding holds the GIL while it optimises (measured: a Python loop in another thread stalls for
the whole solve), so a thread cannot overlap tracking with BA; a process can. ORB-SLAM runs local mapping in
its own thread and tracks against whatever the map is at that moment; here the caller decides on a fixed
frame schedule when a result is applied (``MappingConfig.ba_lag_frames``), so runs stay deterministic: the
worker computes exactly what ``local_bundle_adjustment`` computes in-process (same code, same inputs).

The worker is ``python -m vslam.backend.worker`` (``vslam.childproc``: pickles over its stdin / stdout).
"""

from __future__ import annotations

import subprocess
import sys

from vslam import childproc
from vslam.backend.ba import BackendConfig, BAProblem, BAResult, StereoCamera, local_bundle_adjustment
from vslam.backend.factors import FactorCache


class BAWorker:
    """One child process that solves local BA problems in submission order; started on first use."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen | None = None
        self._waiting = 0

    def start(self) -> None:
        """Start the process now (it imports GTSAM for ~0.3 s while the caller reads its first frames)."""
        if self._proc is None or self._proc.poll() is not None:
            self._proc = childproc.spawn("vslam.backend.worker")
            self._waiting = 0

    def submit(self, problem: BAProblem, camera: StereoCamera, cfg: BackendConfig) -> None:
        self.start()
        childproc.send(self._proc.stdin, (problem, camera, cfg))  # type: ignore[union-attr,arg-type]
        self._waiting += 1

    def result(self) -> BAResult:
        """The oldest submitted problem's result (blocks until the worker has it)."""
        if self._proc is None or self._waiting == 0:
            raise RuntimeError("BAWorker.result: nothing was submitted")
        try:
            status, payload = childproc.receive(self._proc.stdout)  # type: ignore[arg-type,misc]
        except EOFError:
            raise RuntimeError(f"the local BA worker process died (exit code {self._proc.wait()})") from None
        self._waiting -= 1
        if status != "ok":
            raise RuntimeError(f"local BA failed in the worker process: {payload}")
        return payload  # type: ignore[return-value]

    def close(self) -> None:
        childproc.stop(self._proc)
        self._proc = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the child sees EOF and exits on its own
            pass


def _serve() -> None:
    """The worker's loop: (problem, camera, cfg) in on stdin -> ("ok", BAResult) | ("error", text) out."""
    out = childproc.result_stream()  # anything the solver prints goes to stderr, not into the result stream
    inp = sys.stdin.buffer
    cache = FactorCache()  # consecutive windows share most factors (as in the parent's LocalMapper)
    while True:
        try:
            problem, camera, cfg = childproc.receive(inp)  # type: ignore[misc]
        except EOFError:
            return
        try:
            reply: tuple[str, object] = ("ok", local_bundle_adjustment(problem, camera, cfg, cache))
        except Exception as e:  # the parent raises it where it waits
            reply = ("error", f"{type(e).__name__}: {e}")
        childproc.send(out, reply)


if __name__ == "__main__":
    _serve()
