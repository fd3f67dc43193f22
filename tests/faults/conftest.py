"""Small copies of the real subsets for the fault suite (issue 39): the lists, calibration and ground truth are
copied (so a case can break them), the images are symlinks (so a copy costs nothing)."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path
from typing import Callable

import pytest

from vslam.paths import data_root

N = 40  # frames in each copy


def _need(rel: str) -> Path:
    p = data_root() / rel
    if not p.exists():
        pytest.skip(f"real data not found at {p} (set VSLAM_DATA to the folder holding tum/, kitti/, euroc/)")
    return p


def _data_lines(path: Path) -> tuple[list[str], list[str]]:
    """(comment lines, data lines) of a text table."""
    lines = path.read_text().splitlines()
    return [ln for ln in lines if ln.startswith("#")], [ln for ln in lines if ln.strip() and not ln.startswith("#")]


def copy_tum(dst: Path, n: int = N) -> Path:
    """TUM teddy's first ``n`` frames at ``dst`` (a folder named like the original: the name gives the camera)."""
    src = _need("tum/rgbd_dataset_freiburg3_teddy")
    root = dst / src.name
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for name in ("rgb.txt", "depth.txt"):
        head, rows = _data_lines(src / name)
        (root / name).write_text("\n".join(head + rows[:n]) + "\n")
        for row in rows[:n]:
            rel = row.split()[1]
            os.symlink(src / rel, root / rel)
    (root / "groundtruth.txt").write_text((src / "groundtruth.txt").read_text())
    return root


def copy_kitti(dst: Path, n: int = N) -> Path:
    """KITTI 07's first ``n`` frames as ``dst/sequences/07`` + ``dst/poses/07.txt``; returns the sequence folder."""
    src = _need("kitti")
    seq = dst / "sequences" / "07"
    (seq / "image_0").mkdir(parents=True)
    (dst / "poses").mkdir()
    (seq / "calib.txt").write_text((src / "sequences/07/calib.txt").read_text())
    (seq / "times.txt").write_text("\n".join((src / "sequences/07/times.txt").read_text().splitlines()[:n]) + "\n")
    for i in range(n):
        os.symlink(src / f"sequences/07/image_0/{i:06d}.png", seq / f"image_0/{i:06d}.png")
    (dst / "poses" / "07.txt").write_text("\n".join((src / "poses/07.txt").read_text().splitlines()[:n]) + "\n")
    return seq


def replace_data_line(path: Path, k: int, text: str) -> int:
    """Replace the k-th data line (0-based, comments skipped) of a table; returns its 1-based line number."""
    lines = path.read_text().splitlines()
    idx = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")][k]
    lines[idx] = text
    path.write_text("\n".join(lines) + "\n")
    return idx + 1


@pytest.fixture
def tum40(tmp_path: Path) -> Path:
    return copy_tum(tmp_path / "data")


@pytest.fixture
def kitti40(tmp_path: Path) -> Path:
    return copy_kitti(tmp_path / "data")


@pytest.fixture
def cli() -> Callable[..., tuple[int, str, str]]:
    """``vslam ...`` in this process -> (exit code, stdout, stderr). A user mistake must come back as a code and a
    message: an exception escaping ``main`` fails the test on its own."""
    from vslam.cli import main

    def run(*argv: str) -> tuple[int, str, str]:
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main([str(a) for a in argv])
        return rc, out.getvalue(), err.getvalue()

    return run
