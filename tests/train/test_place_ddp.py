"""DistributedDataParallel entry point of the VLADNet training (issue 10): two CPU ranks on gloo, as
``torchrun --nproc_per_node=2`` would start them, run the toy recipe; ``train`` checks that both end with the
same weights, rank 0 alone writes, and the averaged gradients give other weights than one process."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")


def _rank(rank: int, out: str) -> str:
    from vslam.train.place import PlaceTrainConfig, train

    m = train(PlaceTrainConfig(out=out, toy=True, steps=20, threads=1))
    return "ok" if (m != {}) == (rank == 0) else f"rank {rank} returned {sorted(m)}"


def test_two_gloo_ranks_train_the_toy_place_recipe(tmp_path):
    from tests._ddp import run_ranks

    got = run_ranks(_rank, 2, str(tmp_path / "ddp"))
    assert got == {0: "ok", 1: "ok"}, got
    assert (tmp_path / "ddp" / "model.pt").is_file() and (tmp_path / "ddp" / "metrics.json").is_file()
    ddp = torch.load(tmp_path / "ddp" / "last.pt", weights_only=False)["model"]
    from vslam.train.place import PlaceTrainConfig, train

    train(PlaceTrainConfig(out=str(tmp_path / "single"), toy=True, steps=20, threads=1))
    single = torch.load(tmp_path / "single" / "last.pt", weights_only=False)["model"]
    assert all(torch.isfinite(v.float()).all() for v in ddp.values())
    assert any(not torch.equal(single[k], ddp[k]) for k in single if single[k].is_floating_point())
