"""The suite (configs/bench.yaml): its rows, and the sidecar (BENCHMARKS.json) that keeps what they measured."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal


from vslam.bench.checks import Check
from vslam.config import from_dict, load_yaml
from vslam.errors import ConfigError

log = logging.getLogger(__name__)


SIDECAR_VERSION = 1

# stats.csv columns shown in the per-stage table, in pipeline order; other ms_* columns follow
STAGES = ("features", "depth", "pose", "mapping", "map_create", "map_fuse_cull", "map_ba", "map_wait", "map_loop")

PER_FRAME = ("features", "depth", "pose", "total")  # run on every frame: median ms/frame

# kinds run once whatever --repeat says (deterministic, or repeating their measurement inside the job)
SINGLE_RUN_KINDS = ("place", "features", "pose", "detector", "speed", "line_ba", "eval_detector", "detector_speed",
                    "extraction")

# kinds with a table of their own below the SLAM table
OWN_TABLE_KINDS = ("fusion", "imu_preint", "batch", "ab", "sfm") + SINGLE_RUN_KINDS

@dataclass(frozen=True)
class BenchRow:
    name: str
    kind: Literal["run", "synthetic_render", "fusion", "imu_preint", "batch", "place", "features", "pose", "detector",
                  "ab", "speed", "line_ba", "eval_detector", "sfm", "detector_speed", "extraction"] = "run"
    config: str = ""  # pipeline YAML, relative to the suite file's folder's parent (the repo root) or absolute
    set: tuple[str, ...] = ()  # KEY=VALUE overrides
    note: str = ""
    target: str = ""  # the number the row must reach, in words (default: the checks written out)
    check: tuple[Check, ...] = ()  # the target as machine checks (vslam.bench.checks), verdicts computed from the sidecar
    headline: str = ""  # non-empty: a row of the README's results table, this its short "what it measures"
    experiment: str = ""  # kind "fusion": a key of vslam.fusion.experiments.EXPERIMENTS
    # kind "batch" (batch evaluation): the jobs are the grid's cartesian product of KEY: [values] on top of ``set``,
    # run serially, over a process pool and on a local Ray instance of ``workers`` each; wall times compared
    grid: dict[str, Any] = field(default_factory=dict)
    workers: int = 2
    # kind "ab": every grid point run without (A) and with (B) these KEY=VALUE overrides (``batch.ab_result``)
    treatment: tuple[str, ...] = ()
    # kind "run" on composited people (dynamic-object filtering): {data: TUM folder under $VSLAM_DATA, people: 3,
    # seed: 0, coco: coco128}; ``vslam make-dynamic`` writes it once under <runs>/_data and dataset.path points there.
    # Kind "ab" takes seeds: [..] instead of seed: one composite (other walkers) per grid point
    make_dynamic: dict[str, Any] = field(default_factory=dict)

@dataclass(frozen=True)
class BenchSuite:
    title: str = "vslam benchmarks"
    rows: tuple[BenchRow, ...] = field(default_factory=tuple)

def load_suite(path: str | Path) -> BenchSuite:
    data = load_yaml(path)
    suite = from_dict(BenchSuite, data, str(path))
    if not suite.rows:
        raise ConfigError(f"{path}: the suite has no rows")
    return suite

def sidecar_path(output: Path) -> Path:
    """BENCHMARKS.md -> BENCHMARKS.json (the measured rows, machine-readable)."""
    return output.with_suffix(".json")

def load_sidecar(path: Path) -> dict[str, dict[str, Any]]:
    """Rows of an earlier bench run: name -> {"result", "measured", "repeat", "machine"}; {} when absent.

    A sidecar that cannot be read is not trusted: its rows are dropped with a warning, never guessed.
    """
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
        if data.get("version") != SIDECAR_VERSION or not isinstance(data.get("rows"), dict):
            raise ValueError(f"unsupported layout (version {data.get('version')!r})")
        return dict(data["rows"])
    except (ValueError, AttributeError) as e:
        log.warning("%s: ignoring the earlier rows (%s)", path, e)
        return {}

def json_safe(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: json_safe(x) for k, x in v.items()}
    if hasattr(v, "item"):  # numpy scalar
        return json_safe(v.item())
    return v

def entries_by_name(entries: list[tuple[BenchRow, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    return {row.name: e for row, e in entries}
