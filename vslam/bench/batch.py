"""Fan benchmark jobs out (batch evaluation): one after another in fresh processes (the default: clean timings),
over a local process pool (``--jobs N``), or as Ray tasks on a cluster or a local Ray instance (``--ray``).

A job is ``(kind, config, overrides, out_dir)`` as ``vslam.bench.jobs.execute_job`` takes it. Every job runs in a
process of its own (pool: one task per child; Ray: ``max_calls=1``), so peak RSS stays per job and no state
crosses jobs: the metrics equal the serial run's (fixed seeds, no global state), only the timings change, as
parallel jobs share the cores. Ray on a cluster needs vslam (and the data under ``$VSLAM_DATA``) installed on
every node; outputs land in ``out_dir`` on the node that ran the job, the metrics come back to the caller.
"""

from __future__ import annotations

import concurrent.futures as cf
import itertools
import logging
import multiprocessing as mp
import os
import statistics
import sys
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator

from vslam.bench.tables import md_failed_row, md_section
from vslam.errors import ConfigError
from vslam.progress import Progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Job:
    kind: str
    config: str | None
    overrides: dict[str, Any] = field(default_factory=dict)
    out_dir: str = "runs/bench/job"


def _threads_env() -> None:
    """BLAS/OpenMP threads exactly as in the serial path (``bench._worker``), set before numpy loads: another
    thread count may sum in another order, and one rounding difference is enough for a different trajectory."""
    os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))


def _guarded(job: Job) -> dict[str, Any]:
    """Run one job in this (fresh) process; an exception becomes {"error": ...} like the serial path's."""
    _threads_env()
    from vslam.bench.jobs import execute_job

    try:
        return execute_job(job.kind, job.config, job.overrides, job.out_dir)
    except Exception as e:  # report it with the row instead of losing the whole batch
        return {"error": f"{type(e).__name__}: {e}"}


def run_jobs(jobs: list[Job], workers: int = 1, ray: str | None = None,
             progress: Progress | None = None) -> list[dict[str, Any]]:
    """Results of ``jobs`` in order. workers 1 without ray: serial; ray: "" = a local Ray instance with
    ``workers`` CPUs, else a cluster address ("auto", "ray://host:10001", ...). ``progress(done, total)`` as
    each job ends (in parallel: as each one ends in order)."""
    def counted(results: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
        out = []
        for r in results:
            out.append(r)
            if progress is not None:
                progress(len(out), len(jobs))
        return out

    if ray is not None:
        return counted(_run_ray(jobs, workers, ray))
    if workers <= 1:
        from vslam.bench.jobs import run_job

        return counted(run_job(j.kind, j.config, j.overrides, j.out_dir) for j in jobs)
    kw: dict[str, Any] = {"max_workers": workers, "mp_context": mp.get_context("spawn")}
    if sys.version_info >= (3, 11):
        kw["max_tasks_per_child"] = 1  # a fresh process per job: its own peak RSS, nothing cached
    with cf.ProcessPoolExecutor(**kw) as pool:
        return counted(pool.map(_guarded, jobs))


def _run_ray(jobs: list[Job], workers: int, address: str) -> Iterator[dict[str, Any]]:
    try:
        import ray
    except ImportError:
        raise ConfigError("--ray needs the ray package: pip install 'ray>=2.9'") from None
    started = not ray.is_initialized()
    if started:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:  # a local instance: exactly ``workers`` CPUs, no dashboard
            ray.init(num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False,
                     object_store_memory=256 * 2**20)  # results are small; containers have little /dev/shm
    try:
        task = ray.remote(num_cpus=1, max_calls=1)(_guarded)
        for ref in [task.remote(j) for j in jobs]:  # all submitted at once, collected in order
            yield ray.get(ref)
    finally:
        if started:
            ray.shutdown()


# -- grids: parameter sweeps and the batch-scaling row -------------------------------------------------
#: what must come out the same whichever way the jobs ran (timings and memory may differ)
METRICS = ("frames", "tracked", "ate_rmse", "rpe_t", "rpe_r", "path_m")


def grid_sets(grid: dict[str, list[Any]]) -> list[tuple[str, ...]]:
    """{KEY: [values]} -> the ``KEY=VALUE`` overrides of each point of the cartesian product (keys in order)."""
    keys = list(grid)
    for k in keys:
        if not isinstance(grid[k], (list, tuple)) or not grid[k]:
            raise ConfigError(f"grid '{k}': expected a non-empty list of values, got {grid[k]!r}")
    return [tuple(f"{k}={v}" for k, v in zip(keys, vals)) for vals in itertools.product(*(grid[k] for k in keys))]


def grid_overrides(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """{KEY: [values]} -> one nested override dict per point of the cartesian product (keys in order)."""
    from vslam.config import parse_overrides

    return [parse_overrides(list(sets)) for sets in grid_sets(grid)]


def parse_sweep(items: list[str]) -> dict[str, list[Any]]:
    """["KEY=V1,V2", ...] (``vslam bench --sweep``) -> {KEY: [V1, V2]} (values parsed as YAML scalars)."""
    import yaml

    out: dict[str, list[Any]] = {}
    for item in items:
        key, sep, vals = item.partition("=")
        if not sep or not key or not vals:
            raise ConfigError(f"--sweep {item!r}: expected KEY=V1,V2,...")
        out[key.strip()] = [yaml.safe_load(v) for v in vals.split(",")]
    return out


def same_metrics(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> bool:
    return len(a) == len(b) and all(x.get(k) == y.get(k) for x, y in zip(a, b) for k in METRICS)


def batch_row(config: str | None, overrides: dict[str, Any], grid: dict[str, list[Any]], workers: int,
              out_dir: str) -> dict[str, Any]:
    """The batch-scaling check: the grid's jobs serially, over a process pool and on a local Ray instance
    (``workers`` each): wall seconds and whether every job's metrics equal the serial run's."""
    import time

    from vslam.config import deep_merge

    points = grid_overrides(grid)
    out: dict[str, Any] = {"jobs": len(points), "workers": workers}
    modes: dict[str, list[dict[str, Any]]] = {}
    for mode, kw in (("serial", {"workers": 1}), ("pool", {"workers": workers}), ("ray", {"workers": workers, "ray": ""})):
        jobs = [Job("run", config, deep_merge(overrides, p), f"{out_dir}/{mode}-{i:03d}") for i, p in enumerate(points)]
        t0 = time.perf_counter()
        try:
            modes[mode] = run_jobs(jobs, **kw)
        except ConfigError as e:  # no ray installed: say so in the row
            out[f"{mode}_error"] = str(e)
            continue
        out[f"{mode}_s"] = time.perf_counter() - t0
    serial = modes.get("serial", [])
    out["errors"] = sum("error" in r for rs in modes.values() for r in rs)
    for mode in ("pool", "ray"):
        if mode in modes:
            out[f"{mode}_identical"] = same_metrics(serial, modes[mode])
            out[f"{mode}_speedup"] = out["serial_s"] / out[f"{mode}_s"]
    ates = [r["ate_rmse"] for r in serial if r.get("ate_rmse") is not None]
    out["ate_median"] = statistics.median(ates) if ates else None
    return out


def batch_table(rows: list[tuple[Any, dict[str, Any]]]) -> list[str]:
    """BENCHMARKS.md section for kind "batch" rows: (BenchRow, result) pairs."""
    if not rows:
        return []
    lines = md_section("Batch evaluation: serial vs process pool vs Ray",
                       "The same jobs (a grid of sequences x seeds) run one after another, over a local process pool and "
                       "on a local Ray instance; 'same metrics' compares every job's frames, tracked frames, ATE, RPE and "
                       "path length with the serial run's.",
                       ["row", "jobs", "workers", "serial s", "pool s (speed-up)", "Ray s (speed-up)",
                        "same metrics pool / Ray", "median ATE m", "target"])

    def cell(r: dict[str, Any], mode: str) -> str:
        if f"{mode}_s" not in r:
            return f"– ({r.get(mode + '_error', 'not run')})"
        return f"{r[mode + '_s']:.1f} ({r[mode + '_speedup']:.2f}x)"

    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 9))
            continue
        same = " / ".join("yes" if r.get(f"{m}_identical") else ("**no**" if f"{m}_identical" in r else "–") for m in ("pool", "ray"))
        ate = "–" if r.get("ate_median") is None else f"{r['ate_median']:.4f}"
        lines.append(f"| {row.name} | {r['jobs']} | {r['workers']} | {r.get('serial_s', float('nan')):.1f} | {cell(r, 'pool')} | "
                     f"{cell(r, 'ray')} | {same} | {ate} | {row.target} |")
    return lines


def ab_jobs(config: str | None, overrides: dict[str, Any], grid: dict[str, list[Any]], treatment: dict[str, Any],
            out_dir: str) -> list[Job]:
    """Kind "ab" rows: for every grid point (e.g. seeds) a run without (A) and with (B) ``treatment`` on top.
    -> [A_0, B_0, A_1, B_1, ...]."""
    from vslam.config import deep_merge

    jobs = []
    for i, p in enumerate(grid_overrides(grid)):
        base = deep_merge(overrides, p)
        jobs += [Job("run", config, base, f"{out_dir}/a-{i:03d}"), Job("run", config, deep_merge(base, treatment), f"{out_dir}/b-{i:03d}")]
    return jobs


def ab_result(grid: dict[str, list[Any]], results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per grid point ATE of A and B (and local-mapping ms per keyframe), B/A, and the ratio of the means:
    one seed's ratio moves a lot between nearby configurations, a mean over seeds much less
    (docs/benchmarks-history.md, 'Measurements behind settings in the code')."""
    points = [", ".join(s) for s in grid_sets(grid)]
    out: dict[str, Any] = {"points": points, "ate_a": [], "ate_b": [], "kf_ms_a": [], "kf_ms_b": []}
    for a, b in zip(results[0::2], results[1::2]):
        for key, r in (("a", a), ("b", b)):
            out[f"ate_{key}"].append(r.get("ate_rmse"))
            out[f"kf_ms_{key}"].append((r.get("stages") or {}).get("mapping_per_kf"))
    out["errors"] = [r["error"] for r in results if "error" in r]
    both = _ate_pairs(out)
    out["ratios"] = [b / a for a, b in both]
    out["mean_ratio"] = _ratio_of_means(both)
    out["kf_ms_ratio"] = _ratio_of_means([(a, b) for a, b in zip(out["kf_ms_a"], out["kf_ms_b"]) if a and b])
    return out


def _ate_pairs(r: dict[str, Any]) -> list[tuple[float, float]]:
    """(ATE A, ATE B) of the grid points where both runs gave one."""
    return [(a, b) for a, b in zip(r["ate_a"], r["ate_b"]) if a is not None and b is not None]


def _ratio_of_means(pairs: list[tuple[float, float]]) -> float | None:
    """mean(b) / mean(a) over (a, b) pairs; None without pairs."""
    return statistics.mean(b for _, b in pairs) / statistics.mean(a for a, _ in pairs) if pairs else None


def ab_table(rows: list[tuple[Any, dict[str, Any]]]) -> list[str]:
    """BENCHMARKS.md section for kind "ab" rows: (BenchRow, result) pairs."""
    if not rows:
        return []
    lines = md_section("A/B over a grid (seeds, feature budgets)",
                       "The same configuration without (A) and with (B) one change, on every point of a grid (seeds of a "
                       "synthetic sequence; a real sequence has none, so there another knob such as the ORB budget); ATE "
                       "RMSE m per point, B/A per point, and mean ATE B / mean ATE A. Local-mapping ms per keyframe are "
                       "compared as the ratio of their means (timings share the cores with --jobs).",
                       ["row", "change (B)", "points", "ATE A", "ATE B", "B/A", "mean B / mean A", "mapping ms/kf B/A", "target"])

    def vals(xs: list[Any], spec: str) -> str:
        return " / ".join("–" if x is None else format(x, spec) for x in xs)

    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 9))
            continue
        both = _ate_pairs(r)
        mean = "–" if r.get("mean_ratio") is None else (
            f"**{r['mean_ratio']:.2f}x** ({statistics.mean(a for a, _ in both):.4f} → {statistics.mean(b for _, b in both):.4f} m)")
        kf = "–" if r.get("kf_ms_ratio") is None else f"{r['kf_ms_ratio']:.2f}x"
        err = ""
        if r.get("errors"):  # the first error in the table (a cell holds one line); all of them in BENCHMARKS.json
            first = " ".join(str(r["errors"][0]).split()).replace("|", "/")
            err = f" ({len(r['errors'])} runs failed: {first})"
        lines.append(f"| {row.name} | {', '.join(row.treatment)} | {len(r['points'])}{err} | {vals(r['ate_a'], '.4f')} | "
                     f"{vals(r['ate_b'], '.4f')} | {vals(r['ratios'], '.2f')} | {mean} | {kf} | {row.target} |")
    return lines
