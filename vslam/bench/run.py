"""``vslam bench``: run the suite's rows (or some), keep the others from the sidecar, rewrite BENCHMARKS.md."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import logging
from pathlib import Path
from typing import Any, Iterator

from vslam.bench import batch
from vslam.bench.batch import Job, ab_jobs, ab_result, batch_row, grid_sets
from vslam.bench.checks import git_commit
from vslam.bench.jobs import aggregate, machine_info
from vslam.bench.render import render_markdown, write_readme_table
from vslam.bench.suite import (
    SIDECAR_VERSION,
    SINGLE_RUN_KINDS,
    BenchRow,
    BenchSuite,
    entries_by_name,
    json_safe,
    load_sidecar,
    load_suite,
    sidecar_path,
)
from vslam.config import deep_merge, parse_overrides
from vslam.errors import ConfigError
from vslam.progress import Progress

log = logging.getLogger(__name__)


def run_bench(suite_path: str | Path, output: Path, repeat: int = 1, only: list[str] | None = None,
              jobs_dir: Path = Path("runs/bench"), workers: int = 1, ray: str | None = None,
              sweep: dict[str, list[Any]] | None = None, readme: Path | None = None,
              progress: Progress | None = None) -> Path:
    """Run the suite's rows (or those named in ``only``), merge with the rows kept in the sidecar
    ``output.with_suffix('.json')`` and rewrite ``output`` with every row of the suite measured so far.

    workers > 1 / ray: the jobs of all rows go out together (``vslam.bench.batch.run_jobs``). sweep {KEY: [values]}:
    each selected row once per value, as rows ``NAME[KEY=V]`` of a suite of their own (nothing kept). readme: also
    rewrite that file's results table of headline rows (``write_readme_table``; not for a sweep). progress(done,
    total): jobs ended, of all the jobs the rows run."""
    suite = load_suite(suite_path)
    root = Path(suite_path).resolve().parent.parent
    names = {r.name for r in suite.rows}
    unknown = [n for n in only or [] if n not in names]
    if unknown:
        raise ConfigError(f"{suite_path}: no row named {', '.join(unknown)}; rows: {', '.join(sorted(names))}")
    rows = [r for r in suite.rows if not only or r.name in only]
    if sweep:
        rows = _sweep_rows(rows, sweep)
        suite = BenchSuite(f"{suite.title}: sweep of {', '.join(sweep)}", tuple(rows))
        names = {r.name for r in rows}
    side = sidecar_path(output)
    kept = {} if sweep else load_sidecar(side)
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    machine = machine_info()
    commit = {"commit": git_commit(root)}  # the code the rows are measured with (-dirty: with uncommitted changes)
    fresh: dict[str, dict[str, Any]] = {}  # the rows this run measures
    plan: list[tuple[BenchRow, list[Job]]] = []
    ab_labels: dict[str, dict[str, Any]] = {}
    for row in rows:
        cfg = str(Path(row.config) if Path(row.config).is_absolute() else root / row.config) if row.config else None
        over = parse_overrides(list(row.set))
        grid, labels = row.grid, row.grid  # the grid the jobs run over / the one the table names
        if row.make_dynamic and "seeds" in row.make_dynamic:
            grid, labels, kind = _composited_grid(row, jobs_dir)
            over = deep_merge(over, {"dataset": {"kind": kind}})
        elif row.make_dynamic:
            kind, path = _composited(row.make_dynamic, jobs_dir)
            over = deep_merge(over, {"dataset": {"kind": kind, "path": str(path)}})
        if row.kind == "batch":  # runs its own serial / pool / Ray passes
            result = batch_row(cfg, over, row.grid, row.workers, str(jobs_dir / row.name))
            kept[row.name] = fresh[row.name] = {"result": json_safe(result), "measured": now, "repeat": 1,
                                                "machine": machine, **commit}
        elif row.kind == "fusion":  # one seeded, deterministic run: repeating it only costs time
            plan.append((row, [Job("fusion", row.experiment, over, str(jobs_dir / row.name))]))
        elif row.kind == "ab":  # A and B on every grid point, in the same pool as the other rows
            plan.append((row, ab_jobs(cfg, over, grid, parse_overrides(list(row.treatment)), str(jobs_dir / row.name))))
            ab_labels[row.name] = labels
        else:  # a place / features row is deterministic and reports no timing that repeats would steady
            n = 1 if row.kind in SINGLE_RUN_KINDS else max(1, repeat)
            plan.append((row, [Job(row.kind, cfg, over, str(jobs_dir / f"{row.name}-{i}")) for i in range(n)]))
    results = iter(batch.run_jobs([j for _, jobs in plan for j in jobs], workers, ray, progress))
    parallel = {"parallel": workers if ray is None else f"ray:{workers}"} if workers > 1 or ray is not None else {}
    for row, jobs in plan:
        done = [next(results) for _ in jobs]
        result = ab_result(ab_labels[row.name], done) if row.kind == "ab" else aggregate(done)
        if "skipped" in result and row.name in kept:  # e.g. a GPU row on a machine without one
            log.info("%s: %s; its earlier measurement stays", row.name, result["skipped"])
            continue
        kept[row.name] = fresh[row.name] = {"result": json_safe(result), "measured": now,
                                            "repeat": 1 if row.kind == "ab" else len(jobs), "machine": machine,
                                            **parallel, **commit}
    side.parent.mkdir(parents=True, exist_ok=True)
    with _locked(side):
        if not sweep:  # another bench run may have written rows since this one started: theirs stay
            kept = {**load_sidecar(side), **fresh}
        dropped = sorted(set(kept) - names)
        if dropped:
            log.info("%s: rows no longer in the suite dropped: %s", side, ", ".join(dropped))
        entries = [(r, kept[r.name]) for r in suite.rows if r.name in kept]
        side.write_text(json.dumps({"version": SIDECAR_VERSION, "suite": str(suite_path), "written": now,
                                    "machine": machine, "rows": {r.name: e for r, e in entries}},
                                   indent=1, default=float) + "\n")
        output.write_text(render_markdown(suite, entries, now, machine))
        if readme is not None and not sweep:
            write_readme_table(suite, entries_by_name(entries), readme)
    return output


@contextlib.contextmanager
def _locked(side: Path) -> Iterator[None]:
    """Serialise the read-merge-write of the sidecar between bench runs of one checkout (an advisory lock on
    ``BENCHMARKS.json.lock``; none where ``fcntl`` is missing)."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(side.with_name(side.name + ".lock"), "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)

def _composited(spec: dict[str, Any], jobs_dir: Path) -> tuple[str, Path]:
    """(dataset kind, folder) of the make-dynamic sequence a row names, written on first use (seeded: the same
    spec, the same frames)."""
    from vslam.data.composite import GENERATOR_VERSION, make_dynamic, walker_config
    from vslam.data.kitti import is_kitti_layout
    from vslam.paths import data_root

    unknown = set(spec) - {"data", "people", "seed", "coco"}
    if unknown or "data" not in spec:
        raise ConfigError(f"make_dynamic: needs 'data' and takes people, seed (seeds: kind ab), coco; got {sorted(spec)}")
    src = data_root() / str(spec["data"])
    cfg = walker_config(src, int(spec["people"]) if "people" in spec else None, int(spec.get("seed", 0)))
    kitti = is_kitti_layout(src)
    out = (jobs_dir / "_data" / f"{src.name}-people{cfg.n_people}-seed{cfg.seed}-v{GENERATOR_VERSION}").resolve()
    seq = out / "sequences" / src.name if kitti else out
    if not (seq / "boxes.txt").is_file():  # written last
        seq = make_dynamic(src, out, data_root() / str(spec.get("coco", "coco128")), cfg)
    return ("kitti" if kitti else "tum"), seq

def _composited_grid(row: BenchRow, jobs_dir: Path) -> tuple[dict[str, list[Any]], dict[str, list[Any]], str]:
    """Kind "ab" with make_dynamic seeds: (grid over the composites' dataset.path, the same grid named by seed,
    dataset kind). One seed's ATE swings with what its walkers do (a missed close-up, a false box), a mean over
    composites much less."""
    spec = dict(row.make_dynamic)
    seeds = spec.pop("seeds")
    if row.kind != "ab" or "seed" in spec or not isinstance(seeds, list) or not seeds:
        raise ConfigError(f"bench row {row.name}: make_dynamic seeds: [..] is for kind ab rows, without seed")
    made = [_composited({**spec, "seed": s}, jobs_dir) for s in seeds]
    return ({"dataset.path": [str(p) for _, p in made], **row.grid}, {"make_dynamic.seed": list(seeds), **row.grid},
            made[0][0])

def _sweep_rows(rows: list[BenchRow], sweep: dict[str, list[Any]]) -> list[BenchRow]:
    """Each row once per point of the sweep grid, named ``NAME[KEY=V,...]``."""
    points = grid_sets(sweep)
    out = [dataclasses.replace(row, name=f"{row.name}[{','.join(sets)}]", set=row.set + sets)
           for row in rows if row.kind in ("run", "synthetic_render") for sets in points]
    if not out:
        raise ConfigError("--sweep: none of the selected rows is a pipeline run")
    return out
