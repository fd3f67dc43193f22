"""Thread counts while a run lasts: numpy's BLAS and torch's (``RuntimeConfig.blas_threads`` / ``torch_threads``)."""

from __future__ import annotations

import contextlib
import sys
from typing import Iterator

from vslam.childproc import usable_cpus
from vslam.runtime import RuntimeConfig


@contextlib.contextmanager
def blas_threads(cfg: RuntimeConfig | None) -> Iterator[None]:
    """numpy's BLAS thread count for a run (``RuntimeConfig.blas_threads``), restored afterwards."""
    if cfg is None or cfg.blas_threads <= 0:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=cfg.blas_threads, user_api="blas"):
        yield


def torch_thread_count(cfg: RuntimeConfig) -> int:
    """``RuntimeConfig.torch_threads``, or 0 resolved: the CPUs, less one for the tracking thread when the front end
    runs beside it (on a thread or in the child process, which uses the same count)."""
    return cfg.torch_threads or max(1, usable_cpus() - (1 if cfg.frontend_thread else 0))


@contextlib.contextmanager
def torch_threads(cfg: RuntimeConfig | None) -> Iterator[None]:
    """torch's intra-op thread count for a run (``RuntimeConfig.torch_threads``), restored afterwards; nothing when
    the run loaded no network (torch not imported)."""
    torch = sys.modules.get("torch")
    if cfg is None or torch is None:
        yield
        return
    n = torch_thread_count(cfg)
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
