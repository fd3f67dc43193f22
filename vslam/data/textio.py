"""Strict parsing of the whitespace/CSV text tables every benchmark uses.

Every problem is reported as a DatasetError naming the file and 1-based line,
so a user can open the file at the right place.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vslam.errors import DatasetError


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DatasetError(path, f"missing {what}")
    return path


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise DatasetError(path, f"missing {what} folder")
    return path


def read_rows(
    path: Path,
    ncols: int | tuple[int, int],
    *,
    delimiter: str | None = None,
    numeric_cols: int | None = None,
    allow_nan: bool = False,
) -> tuple[list[int], list[list[str]]]:
    """Rows of a text table, skipping blank and '#' lines.

    ncols: exact count, or (min, max) inclusive. numeric_cols: how many
    leading columns must parse as finite floats (default: all).
    Returns (line numbers, rows of stripped string fields).
    """
    require_file(path, "file")
    lo, hi = (ncols, ncols) if isinstance(ncols, int) else ncols
    want = f"{lo}" if lo == hi else f"{lo} to {hi}"
    lines: list[int] = []
    rows: list[list[str]] = []
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DatasetError(path, "not a text file") from None
    for i, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#") or s.startswith("%"):
            continue
        fields = [f.strip() for f in s.split(delimiter)] if delimiter else s.split()
        if fields and fields[-1] == "" and delimiter:
            fields = fields[:-1]
        if not lo <= len(fields) <= hi:
            raise DatasetError(path, f"expected {want} columns, found {len(fields)}", i)
        n_num = len(fields) if numeric_cols is None else numeric_cols
        for j in range(n_num):
            try:
                v = float(fields[j])
            except ValueError:
                raise DatasetError(path, f"column {j + 1} is not a number: {fields[j]!r}", i) from None
            if not allow_nan and not math.isfinite(v):
                raise DatasetError(path, f"column {j + 1} is not finite: {fields[j]!r}", i)
        lines.append(i)
        rows.append(fields)
    return lines, rows


def read_numeric(path: Path, ncols: int | tuple[int, int], *, delimiter: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(line numbers (N,), values (N, ncols) float64) of an all-numeric table."""
    lines, rows = read_rows(path, ncols, delimiter=delimiter)
    if isinstance(ncols, tuple) and rows and len({len(r) for r in rows}) > 1:
        first = len(rows[0])
        bad = next(k for k, r in enumerate(rows) if len(r) != first)
        raise DatasetError(path, f"expected {first} columns like the first row, found {len(rows[bad])}", lines[bad])
    width = len(rows[0]) if rows else (ncols if isinstance(ncols, int) else ncols[0])
    values = np.array([[float(v) for v in r] for r in rows], dtype=np.float64).reshape(-1, width)
    return np.asarray(lines, dtype=np.int64), values


def check_increasing(path: Path, t: np.ndarray, lines: np.ndarray, *, strict: bool = True) -> None:
    """Raise at the first timestamp that does not increase (duplicates too when strict)."""
    if len(t) < 2:
        return
    d = np.diff(t)
    bad = np.flatnonzero(d <= 0 if strict else d < 0)
    if len(bad):
        k = int(bad[0]) + 1
        kind = "repeats" if d[bad[0]] == 0 else "goes back in time"
        raise DatasetError(path, f"timestamp {float(t[k])!r} {kind} (previous {float(t[k - 1])!r}); timestamps must increase", int(lines[k]))


QUATERNION_TOLERANCE = 1e-3  # | |q| - 1 | allowed: files print 4-9 decimals; a larger error is not rounding


def check_unit_quaternions(path: Path, q: np.ndarray, lines: np.ndarray, first_col: int) -> None:
    """Raise at the first quaternion (rows of ``q``, any component order) that is not unit length: a zero or
    scaled quaternion is a broken line, and normalising it silently would turn it into some other rotation."""
    if len(q) == 0:
        return
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_TOLERANCE)
    if len(bad):
        k = int(bad[0])
        cols = f"columns {first_col}-{first_col + 3}"
        raise DatasetError(path, f"quaternion ({cols}) has norm {norm[k]:.6g}, expected unit length "
                                 f"(within {QUATERNION_TOLERANCE:g})", int(lines[k]))


def check_rotations(path: Path, R: np.ndarray, lines: np.ndarray, tol: float = 1e-2) -> None:
    """Raise at the first 3x3 block that is not a rotation (R^T R = I, det +1, to ``tol``): KITTI-style pose
    files print ~6 significant digits, so a real rotation is orthonormal to ~1e-6."""
    if len(R) == 0:
        return
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > tol) | (np.linalg.det(R) < 0))
    if len(bad):
        k = int(bad[0])
        raise DatasetError(path, f"pose's 3x3 part is not a rotation (|R^T R - I| = {err[k]:.3g}, det "
                                 f"{np.linalg.det(R[k]):.3g})", int(lines[k]))


def read_yaml_mapping(path: Path) -> tuple[dict[str, Any], dict[str, int]]:
    """A YAML file's top-level mapping and the 1-based line of each key.

    OpenCV ``FileStorage`` files (EuRoC ``sensor.yaml``) start with a
    ``%YAML:1.0`` directive that PyYAML rejects; such lines are blanked so
    that line numbers in errors still match the file.
    """
    require_file(path, "YAML file")
    lines = path.read_text().splitlines()
    clean = "\n".join("" if ln.lstrip().startswith("%YAML") else ln for ln in lines)
    try:
        node = yaml.compose(clean, Loader=yaml.SafeLoader)
        data = yaml.safe_load(clean)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise DatasetError(path, f"not valid YAML: {problem}", mark.line + 1 if mark else None) from None
    if not isinstance(data, dict) or node is None:
        raise DatasetError(path, "expected a mapping of keys at the top level")
    key_lines = {str(k.value): k.start_mark.line + 1 for k, _ in node.value}
    return data, key_lines


def yaml_numbers(path: Path, data: dict[str, Any], lines: dict[str, int], key: str, count: int | tuple[int, ...]) -> list[float]:
    """``data[key]`` as a list of finite floats of an allowed length, else DatasetError at the key's line."""
    counts = (count,) if isinstance(count, int) else count
    if key not in data:
        raise DatasetError(path, f"missing key {key!r}")
    value = data[key]
    if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise DatasetError(path, f"{key!r} must be a list of numbers, got {value!r}", lines.get(key))
    if len(value) not in counts:
        want = " or ".join(str(c) for c in counts)
        raise DatasetError(path, f"{key!r} must have {want} numbers, found {len(value)}", lines.get(key))
    if not all(np.isfinite(value)):
        raise DatasetError(path, f"{key!r} holds a value that is not finite", lines.get(key))
    return [float(v) for v in value]
