"""DistributedDataParallel entry point of the detector training (issue 10): two CPU ranks on gloo, as
``torchrun --nproc_per_node=2`` would start them, train the toy recipe; ``train`` itself checks that both end
with the same weights, and the averaged gradients give other weights than a single-process run."""

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
    import vslam.dynamic.train as tr

    torch.set_num_threads(1)
    try:
        tr.train(tr.TrainConfig(out=out, toy=True, synthetic_frames=8, synthetic_stride=2, threads=1))
        q.put((rank, "ok"))
    except BaseException as e:  # pragma: no cover - reported to the parent
        q.put((rank, f"{type(e).__name__}: {e}"))


def test_two_gloo_ranks_train_the_toy_recipe(tmp_path):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    port = _free_port()
    procs = [ctx.Process(target=_rank, args=(r, 2, port, str(tmp_path), q)) for r in range(2)]
    for p in procs:
        p.start()
    got = dict(q.get(timeout=300) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    assert got == {0: "ok", 1: "ok"}, got  # train() raises on a rank whose weights left the others'
    ddp = torch.load(tmp_path / "last.pt", weights_only=False)["model"]
    assert (tmp_path / "model.pt").is_file() and (tmp_path / "metrics.json").is_file()  # rank 0 wrote them
    log = (tmp_path / "log.csv").read_text().splitlines()
    assert log[0].startswith("iteration") and len(log) == 1 + 3  # one writer: iterations 0, 10, 19
    assert all(torch.isfinite(v.float()).all() for v in ddp.values())
    import vslam.dynamic.train as tr

    tr.train(tr.TrainConfig(out=str(tmp_path / "single"), toy=True, synthetic_frames=8, synthetic_stride=2, threads=1))
    single = torch.load(tmp_path / "single" / "last.pt", weights_only=False)["model"]
    assert any(not torch.equal(single[k], ddp[k]) for k in single if single[k].is_floating_point())
