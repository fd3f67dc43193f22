"""DistributedDataParallel plumbing shared by the trainers (``vslam train detector`` / ``place`` / ``keypoints``).

``torchrun --nproc_per_node=N -m vslam.cli train <model> ...`` starts N ranks; each trainer runs through
``launch(device, body)`` (joins the group: NCCL on CUDA, one GPU per local rank; gloo on CPU; leaves it after),
draws its own samples per rank, wraps its model in ``DistributedDataParallel`` (gradients averaged over ranks),
lets rank 0 alone write, and ends with ``check_in_sync`` (every rank must hold the same weights). Without
torchrun: one rank, no-ops.
"""

from __future__ import annotations

import os

import torch


def world() -> tuple[int, int, int]:
    """(rank, world size, local rank) from torchrun's RANK / WORLD_SIZE / LOCAL_RANK; (0, 1, 0) without it."""
    env = os.environ
    return int(env.get("RANK", 0)), int(env.get("WORLD_SIZE", 1)), int(env.get("LOCAL_RANK", 0))


def start(dev: torch.device) -> tuple[int, int, torch.device]:
    """Join the process group when several ranks run. -> (rank, world size, this rank's device)."""
    rank, n, local = world()
    if n > 1:
        import torch.distributed as dist

        if dev.type == "cuda":
            dev = torch.device("cuda", local)
            torch.cuda.set_device(dev)
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return rank, n, dev


def launch(dev: torch.device, body):
    """Join the process group, run ``body(device, rank, n_ranks)`` on this rank's device, leave the group
    (also on an error) -> what ``body`` returned. The one entry every trainer goes through."""
    rank, n, dev = start(dev)
    try:
        return body(dev, rank, n)
    finally:
        stop(n)


def stop(n_ranks: int) -> None:
    if n_ranks > 1:
        torch.distributed.destroy_process_group()


def wrap(model: torch.nn.Module, dev: torch.device, n_ranks: int, find_unused: bool = False) -> torch.nn.Module:
    """The module the forward pass goes through: DDP (broadcasts rank 0's weights now) or the model itself.
    ``find_unused``: a stage whose loss leaves some parameters without gradient (a head trained later)."""
    if n_ranks <= 1:
        return model
    return torch.nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None,
                                                     find_unused_parameters=find_unused)


def check_in_sync(model: torch.nn.Module) -> None:
    """Every rank must end with the same weights (DDP broadcasts them once and averages every gradient):
    a checksum gathered from all ranks, RuntimeError if one differs."""
    import torch.distributed as dist

    v = torch.stack([p.detach().double().sum() for p in model.parameters()]).sum().reshape(1)
    every = [torch.zeros_like(v) for _ in range(dist.get_world_size())]
    dist.all_gather(every, v)
    if any(not torch.equal(x, every[0]) for x in every):
        raise RuntimeError(f"DDP ranks ended with different weights (checksums {[float(x) for x in every]})")
