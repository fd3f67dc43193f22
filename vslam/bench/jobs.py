"""One job of a row, in a fresh process (``run_job``) or in this one (``execute_job``), and the machine it ran on."""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import statistics
from pathlib import Path
from typing import Any


from vslam.bench.kinds import job_function


def execute_job(kind: str, config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """One job in this process -> its result row (``vslam.bench.batch`` calls this in its worker processes)."""
    return job_function(kind)(config, overrides, out_dir)


def _worker(kind: str, config: str | None, overrides: dict[str, Any], out_dir: str, q: Any) -> None:
    try:
        os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))
        q.put(("ok", execute_job(kind, config, overrides, out_dir)))
    except BaseException as e:  # report to the parent instead of dying silently
        q.put(("error", f"{type(e).__name__}: {e}"))

def run_job(kind: str, config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_worker, args=(kind, config, overrides, out_dir, q))
    p.start()
    status, payload = q.get()
    p.join()
    if status != "ok":
        return {"error": payload}
    return payload

def machine_info() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import psutil

        mem = f"{psutil.virtual_memory().total / 2**30:.0f} GiB RAM"
    except ImportError:
        mem = "RAM unknown"
    return f"{cpu}, {os.cpu_count()} logical cores, {mem}, {platform.system()} {platform.release()}, Python {platform.python_version()}"

def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": runs[0]["error"]}
    agg = dict(ok[0])
    for key in ("ate_rmse", "fps", "ms_per_frame", "rpe_t", "rpe_r", "peak_rss_mb"):
        vals = [r[key] for r in ok if r.get(key) is not None]
        if vals:
            agg[key] = statistics.median(vals)
            agg[key + "_spread"] = max(vals) - min(vals)
    stage_runs = [r["stages"] for r in ok if r.get("stages")]
    if stage_runs:
        names = list(dict.fromkeys(k for st in stage_runs for k in st))
        agg["stages"] = {k: statistics.median(st[k] for st in stage_runs if k in st) for k in names}
    agg["n_runs"] = len(ok)
    agg["identical"] = len({round(r.get("ate_rmse", 0.0), 12) for r in ok}) == 1
    return agg
