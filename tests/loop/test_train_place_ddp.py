"""DistributedDataParallel entry point of the VLADNet training (issue 10): two CPU ranks on gloo, as
``torchrun --nproc_per_node=2`` would start them, run the toy recipe; ``train`` checks that both end with the
same weights, rank 0 alone writes, and the averaged gradients give other weights than one process."""

from __future__ import annotations

import os
import socket

import pytest

torch = pytest.importorskip("torch")
mp = pytest.importorskip("torch.multiprocessing")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank(rank: int, world: int, port: int, out: str, q) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank),
                      MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    from vslam.loop.train_place import PlaceTrainConfig, train

    try:
        m = train(PlaceTrainConfig(out=out, toy=True, steps=20, threads=1))
        q.put((rank, "ok" if (m != {}) == (rank == 0) else f"rank {rank} returned {sorted(m)}"))
    except BaseException as e:  # pragma: no cover - reported to the parent
        q.put((rank, f"{type(e).__name__}: {e}"))


def test_two_gloo_ranks_train_the_toy_place_recipe(tmp_path):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_rank, args=(r, 2, port, str(tmp_path / "ddp"), q)) for r in range(2)]
    for p in procs:
        p.start()
    got = dict(q.get(timeout=300) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    assert got == {0: "ok", 1: "ok"}, got
    assert (tmp_path / "ddp" / "model.pt").is_file() and (tmp_path / "ddp" / "metrics.json").is_file()
    ddp = torch.load(tmp_path / "ddp" / "last.pt", weights_only=False)["model"]
    from vslam.loop.train_place import PlaceTrainConfig, train

    train(PlaceTrainConfig(out=str(tmp_path / "single"), toy=True, steps=20, threads=1))
    single = torch.load(tmp_path / "single" / "last.pt", weights_only=False)["model"]
    assert all(torch.isfinite(v.float()).all() for v in ddp.values())
    assert any(not torch.equal(single[k], ddp[k]) for k in single if single[k].is_floating_point())
