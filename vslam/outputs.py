"""The output folder of a run: made ready before the run, written so that a failure never leaves a lie.

Two kinds of files: the ones written as frames are produced (``trajectory.*.txt``, ``stats.csv``; flushed per
line, so a crash keeps every frame done so far) and the ones written once at the end (ground truth, map,
report, final trajectory). The latter go to a temporary name and are renamed into place: a full disk or a
kill leaves the file complete or absent, never cut. An earlier run's files in the folder are removed before
a new run starts, so a report or a ground truth of another sequence never sits beside the new trajectory.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from vslam.errors import VslamError

log = logging.getLogger(__name__)

# What ``vslam run`` may write into its folder (names and glob patterns); nothing else there is touched.
RUN_FILES = ("config.yaml", "stats.csv", "trajectory.*.txt", "trajectory_final.tum.txt", "groundtruth.tum.txt",
             "keyframes.tum.txt", "map.ply", "map_lines.ply", "map.vslam.npz", "loops.json", "profile.json",
             "report")
# errno values that mean "this output cannot be written" rather than a bug
OUTPUT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR,
                           errno.EISDIR, errno.EEXIST, errno.EIO})


class OutputError(VslamError):
    """The output folder cannot be made or written (a file in the way, no permission, a full disk)."""


def prepare_run_dir(out: Path, keep: tuple[str | Path, ...] = ()) -> list[str]:
    """Make ``out`` ready for a run: a writable folder without an earlier run's files (but the files in
    ``keep``: inputs of this run, such as the map it loads). Returns the names removed."""
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output.dir names a file, expected a folder (or a path to create)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{out}: cannot create the output folder ({e.strerror or e})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: the output folder is not writable")
    removed = []
    kept = {Path(k).resolve() for k in keep if k}
    for pattern in RUN_FILES:
        for p in sorted(out.glob(pattern)):
            if p.resolve() in kept:
                continue
            try:
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
            except OSError as e:
                raise OutputError(f"{p}: cannot remove the earlier run's file ({e.strerror or e})") from None
            removed.append(p.name)
    for p in out.glob(".*.tmp-*"):  # temporaries of a run killed mid-write
        with contextlib.suppress(OSError):
            p.unlink()
    if removed:
        log.warning("%s held an earlier run: removed its %s", out, ", ".join(removed))
    return removed


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` (same suffix, for writers that pick the format from it), renamed to
    ``path`` when the block ends without error, removed otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            with contextlib.suppress(OSError):
                tmp.unlink()


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", **kwargs) -> Iterator[IO]:
    """``open(path, mode)`` through ``atomic_path``: the file appears whole when the block ends, or not at all."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as f:
        yield f


def write_text(path: str | Path, text: str) -> Path:
    with atomic_open(path, "w") as f:
        f.write(text)
    return Path(path)


def write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_open(path, "wb") as f:
        f.write(data)
    return Path(path)


def describe_failure(out: Path, e: OSError) -> str:
    """One line for an output that could not be written: which file, why, and what the folder holds now."""
    what = f"{e.filename}: " if e.filename else f"{out}: "
    try:
        have = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    except OSError:
        have = []
    held = f"; {out} holds {', '.join(have)} (files not listed were not written)" if have else ""
    return f"{what}{e.strerror or e}{held}"


def write_map_ply(path: Path, xyz: np.ndarray) -> Path:
    """(N,3) world points -> binary PLY point cloud (x, y, z doubles), the layout open3d writes. Written here, not
    by open3d: importing it for this costs resident memory at the end of every run (docs/speed.md)."""
    xyz = np.ascontiguousarray(xyz, dtype="<f8").reshape(-1, 3)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\nproperty double x\n"
            "property double y\nproperty double z\nend_header\n")
    with atomic_open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(xyz.tobytes())
    return path
