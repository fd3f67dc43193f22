"""The bench kinds: what a row of each kind runs (``job``, one job of the row) and how its rows are tabled
(``table``), one module per kind (or per pair of close kinds). Targets are ``"module:function"`` strings imported
on first use: rendering BENCHMARKS.md imports no network, running a SLAM row no detector evaluation.

Adding a kind: a module here with ``job(config, overrides, out_dir) -> dict`` (the result row the sidecar keeps)
and ``table(rows) -> list[str]`` (Markdown lines from [(row, result)]), one entry below, the kind's name in
``BenchRow.kind``; rows of ``run`` and ``synthetic_render`` share the main SLAM table instead.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable


@dataclass(frozen=True)
class Kind:
    job: str  # "module:function" (config, overrides, out_dir) -> result dict; "": run_bench plans the row's jobs
    table: str = ""  # "module:function" [(row, result)] -> Markdown lines; "" = the main SLAM table


_K = "vslam.bench.kinds."
KINDS: dict[str, Kind] = {
    "run": Kind(_K + "run:job"),
    "synthetic_render": Kind(_K + "run:job_render"),
    "fusion": Kind(_K + "fusion:job", _K + "fusion:table"),
    "imu_preint": Kind(_K + "inertial:job", _K + "inertial:table"),
    "place": Kind(_K + "place:job", _K + "place:table"),
    "features": Kind(_K + "features:job", _K + "features:table"),
    "pose": Kind(_K + "features:job_pose", _K + "features:pose_table"),
    "detector": Kind(_K + "detector:job", _K + "detector:table"),
    "eval_detector": Kind(_K + "detector:job_eval", _K + "detector:eval_table"),
    "speed": Kind(_K + "speed:job", _K + "speed:table"),
    "detector_speed": Kind(_K + "detector_speed:job", _K + "detector_speed:table"),
    "line_ba": Kind(_K + "speed:job_line_ba", _K + "speed:line_ba_table"),
    "extraction": Kind(_K + "extraction:job", _K + "extraction:table"),
    "sfm": Kind(_K + "sfm:job", _K + "sfm:table"),
    "batch": Kind("", "vslam.bench.batch:batch_table"),  # its own serial / pool / Ray passes of run jobs
    "ab": Kind("", "vslam.bench.batch:ab_table"),  # run jobs without and with the treatment
}
# the order of the own tables in BENCHMARKS.md, after the main SLAM table
TABLE_ORDER = tuple(k for k, v in KINDS.items() if v.table)


def _resolve(target: str) -> Callable[..., Any]:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def job_function(kind: str) -> Callable[[str | None, dict[str, Any], str], dict[str, Any]]:
    """The job of ``kind`` (batch and ab rows are made of ``run`` jobs)."""
    if kind not in KINDS or not KINDS[kind].job:
        raise ValueError(f"no job function for bench kind {kind!r}")
    return _resolve(KINDS[kind].job)


def table_function(kind: str) -> Callable[[list[tuple[Any, dict[str, Any]]]], list[str]]:
    return _resolve(KINDS[kind].table)
