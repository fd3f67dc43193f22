"""Helpers for tests of child processes."""

from __future__ import annotations

import time
from pathlib import Path


def environ_after_exec(pid: int, module: bytes) -> list[bytes]:
    """The child's environment once it runs ``python -m module``: between fork and exec /proc shows the parent's
    (that race made the BA-worker test of test_pipeline fail once in a while)."""
    for _ in range(500):
        if module in Path(f"/proc/{pid}/cmdline").read_bytes():
            return Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        time.sleep(0.01)
    raise AssertionError(f"process {pid} never ran {module!r}")
