"""DistributedDataParallel entry point of the detector training (issue 10): two CPU ranks on gloo, as
``torchrun --nproc_per_node=2`` would start them, train the toy recipe; ``train`` itself checks that both end
with the same weights, and the averaged gradients give other weights than a single-process run."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")


def _rank(rank: int, out: str) -> str:
    import vslam.train.detector as tr

    torch.set_num_threads(1)
    tr.train(tr.TrainConfig(out=out, toy=True, synthetic_frames=8, synthetic_stride=2, threads=1))
    return "ok"


def test_two_gloo_ranks_train_the_toy_recipe(tmp_path):
    from tests._ddp import run_ranks

    got = run_ranks(_rank, 2, str(tmp_path))
    assert got == {0: "ok", 1: "ok"}, got  # train() raises on a rank whose weights left the others'
    ddp = torch.load(tmp_path / "last.pt", weights_only=False)["model"]
    assert (tmp_path / "model.pt").is_file() and (tmp_path / "metrics.json").is_file()  # rank 0 wrote them
    log = (tmp_path / "log.csv").read_text().splitlines()
    assert log[0].startswith("iteration") and len(log) == 1 + 3  # one writer: iterations 0, 10, 19
    assert all(torch.isfinite(v.float()).all() for v in ddp.values())
    import vslam.train.detector as tr

    tr.train(tr.TrainConfig(out=str(tmp_path / "single"), toy=True, synthetic_frames=8, synthetic_stride=2, threads=1))
    single = torch.load(tmp_path / "single" / "last.pt", weights_only=False)["model"]
    assert any(not torch.equal(single[k], ddp[k]) for k in single if single[k].is_floating_point())
