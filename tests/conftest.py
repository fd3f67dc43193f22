"""Shared fixtures: the real data root (skip with a reason when absent) and a tiny synthetic sequence."""

from __future__ import annotations

from pathlib import Path

import pytest

from vslam.paths import data_root


def _need(rel: str) -> Path:
    p = data_root() / rel
    if not p.exists():
        pytest.skip(f"real data not found at {p} (set VSLAM_DATA to the folder holding tum/, kitti/, euroc/)")
    return p


@pytest.fixture
def tum_teddy() -> Path:
    return _need("tum/rgbd_dataset_freiburg3_teddy")


@pytest.fixture
def kitti_root() -> Path:
    return _need("kitti")


@pytest.fixture
def euroc_v101() -> Path:
    return _need("euroc/V1_01_easy_micro")


@pytest.fixture
def evo_traj_dir() -> Path:
    return _need("trajectories/evo")
