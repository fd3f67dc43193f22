"""Run a function on several CPU ranks as ``torchrun`` would (gloo), for the DDP entry-point tests."""

from __future__ import annotations

import os
import socket

import torch.multiprocessing as mp


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _entry(target, rank: int, world: int, port: int, args: tuple, q) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    try:
        q.put((rank, target(rank, *args)))
    except BaseException as e:  # pragma: no cover - reported to the parent
        q.put((rank, f"{type(e).__name__}: {e}"))


def run_ranks(target, world: int, *args, timeout: float = 300) -> dict[int, str]:
    """``target(rank, *args)`` (a module-level function returning a status string) on ``world`` spawned ranks;
    -> {rank: status, or the exception it raised}."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_entry, args=(target, r, world, port, args, q)) for r in range(world)]
    for p in procs:
        p.start()
    got = dict(q.get(timeout=timeout) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    return got
