"""`vslam bench`: run a suite of (config, sequence) rows and rewrite BENCHMARKS.md.

Each run happens in a fresh spawned process so its peak memory is its own
and one row cannot warm caches for the next. Timings are only compared as
ratios inside one BENCHMARKS.md (same machine, same run).
"""

from __future__ import annotations

import datetime as _dt
import multiprocessing as mp
import os
import platform
import resource
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from vslam.config import deep_merge, from_dict, load_yaml, parse_overrides
from vslam.errors import ConfigError


@dataclass(frozen=True)
class BenchRow:
    name: str
    kind: Literal["run", "synthetic_render", "fusion"] = "run"
    config: str = ""  # pipeline YAML, relative to the suite file's folder's parent (the repo root) or absolute
    set: tuple[str, ...] = ()  # KEY=VALUE overrides
    note: str = ""
    target: str = ""  # the number the issue asks for, shown beside ours
    experiment: str = ""  # kind "fusion": a key of vslam.fusion.experiments.EXPERIMENTS


@dataclass(frozen=True)
class BenchSuite:
    title: str = "vslam benchmarks"
    rows: tuple[BenchRow, ...] = field(default_factory=tuple)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _job_run(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.pipeline import Pipeline, PipelineConfig

    cfg = PipelineConfig.load(config, deep_merge(overrides, {"output": {"dir": out_dir}}))
    res = Pipeline(cfg).run()
    row: dict[str, Any] = {"frames": len(res.trajectory), "tracked": int(res.tracked.sum()), "fps": res.fps,
                           "ms_per_frame": 1e3 * res.seconds / max(1, len(res.trajectory))}
    if res.eval is not None:
        row["ate_rmse"] = res.eval.ate.translation.rmse
        row["align"] = res.eval.alignment.method
        row["path_m"] = res.eval.gt_length_m
        first = res.eval.rpe[0] if res.eval.rpe else None
        if first is not None:
            row["rpe_t"] = first.translation.rmse
            row["rpe_r"] = first.rotation_deg.rmse
            row["rpe_delta"] = first.label
    row["peak_rss_mb"] = _peak_rss_mb()
    return row


def _job_render(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

    data = load_yaml(config) if config else {}
    data = deep_merge(((data.get("dataset") or {}).get("synthetic") or {}) if "dataset" in data else data, overrides.get("dataset", {}).get("synthetic", {}))
    seq = SyntheticSequence(from_dict(SyntheticConfig, data, config or "<render>"), sensor="stereo")  # with the right image
    t0 = time.perf_counter()
    n = 0
    for _ in seq:
        n += 1
    dt = time.perf_counter() - t0
    return {"frames": n, "fps": n / dt, "ms_per_frame": 1e3 * dt / n, "peak_rss_mb": _peak_rss_mb()}


def _job_fusion(experiment: str, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.fusion.experiments import EXPERIMENTS

    if experiment not in EXPERIMENTS:
        raise ConfigError(f"unknown fusion experiment {experiment!r}; known: {', '.join(sorted(EXPERIMENTS))}")
    t0 = time.perf_counter()
    m = EXPERIMENTS[experiment](Path(out_dir), seed=int(overrides.get("seed", 0)), quick=bool(overrides.get("quick", False)))
    return {"headline": m.get("headline", ""), "seed_claim": m.get("seed_claim", ""), "seconds": time.perf_counter() - t0,
            "report": str(Path(out_dir) / "report.md"), "peak_rss_mb": _peak_rss_mb()}


def _worker(kind: str, config: str | None, overrides: dict[str, Any], out_dir: str, q: Any) -> None:
    try:
        os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count() or 1))
        if kind == "fusion":
            q.put(("ok", _job_fusion(str(config), overrides, out_dir)))
            return
        fn = _job_run if kind == "run" else _job_render
        q.put(("ok", fn(config, overrides, out_dir)))
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


def _fmt(v: Any, spec: str) -> str:
    return "–" if v is None else format(v, spec)


def _aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in runs if "error" not in r]
    if not ok:
        return {"error": runs[0]["error"]}
    agg = dict(ok[0])
    for key in ("ate_rmse", "fps", "ms_per_frame", "rpe_t", "rpe_r", "peak_rss_mb"):
        vals = [r[key] for r in ok if r.get(key) is not None]
        if vals:
            agg[key] = statistics.median(vals)
            agg[key + "_spread"] = max(vals) - min(vals)
    agg["n_runs"] = len(ok)
    agg["identical"] = len({round(r.get("ate_rmse", 0.0), 12) for r in ok}) == 1
    return agg


def load_suite(path: str | Path) -> BenchSuite:
    data = load_yaml(path)
    suite = from_dict(BenchSuite, data, str(path))
    if not suite.rows:
        raise ConfigError(f"{path}: the suite has no rows")
    return suite


def run_bench(suite_path: str | Path, output: Path, repeat: int = 1, only: list[str] | None = None,
              jobs_dir: Path = Path("runs/bench")) -> Path:
    suite = load_suite(suite_path)
    root = Path(suite_path).resolve().parent.parent
    rows = [r for r in suite.rows if not only or r.name in only]
    if not rows:
        raise ConfigError(f"{suite_path}: no row named {', '.join(only or [])}")
    results = []
    for row in rows:
        if row.kind == "fusion":  # one seeded, deterministic run: repeating it only costs time
            results.append((row, _aggregate([run_job("fusion", row.experiment, parse_overrides(list(row.set)),
                                                     str(jobs_dir / row.name))])))
            continue
        cfg = None
        if row.config:
            cfg = str(Path(row.config) if Path(row.config).is_absolute() else root / row.config)
        over = parse_overrides(list(row.set))
        runs = [run_job(row.kind, cfg, over, str(jobs_dir / f"{row.name}-{i}")) for i in range(max(1, repeat))]
        results.append((row, _aggregate(runs)))
    output.write_text(render_markdown(suite, results, repeat))
    return output


def render_markdown(suite: BenchSuite, results: list[tuple[BenchRow, dict[str, Any]]], repeat: int) -> str:
    now = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    lines = [
        f"# {suite.title}",
        "",
        f"Written by `vslam bench` on {now}.",
        f"Machine: {machine_info()}.",
        f"Each row: {repeat} run(s) in a fresh process; numbers are medians, ± is max−min over the runs.",
        "Timings are comparable only within this file (same machine, same session).",
        "",
        "| row | frames (tracked) | path m | ATE RMSE m | ATE % of path | align | RPE trans / rot | frames/s | ms/frame | peak RSS MB | deterministic | target |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row, r in results:
        if row.kind == "fusion":
            continue
        if "error" in r:
            lines.append(f"| {row.name} | **failed**: {r['error']} | | | | | | | | | | {row.target} |")
            continue
        ate = _fmt(r.get("ate_rmse"), ".4f")
        if r.get("ate_rmse_spread") and repeat > 1:
            ate += f" ± {r['ate_rmse_spread']:.4f}"
        rpe = "–" if r.get("rpe_t") is None else f"{r['rpe_t']:.4f} m / {r['rpe_r']:.3f}° per {r['rpe_delta']}"
        tracked = f"{r['frames']} ({r['tracked']})" if "tracked" in r else f"{r['frames']}"
        det = ("yes" if r.get("identical") else "**no**") if repeat > 1 and "ate_rmse" in r else "–"
        path = r.get("path_m")
        pct = "–" if path is None or r.get("ate_rmse") is None or path <= 0 else f"{100 * r['ate_rmse'] / path:.2f}"
        lines.append(
            f"| {row.name} | {tracked} | {_fmt(path, '.2f')} | {ate} | {pct} | {r.get('align', '–')} | {rpe} | {r['fps']:.1f} | {r['ms_per_frame']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {det} | {row.target} |"
        )
    fusion = [(row, r) for row, r in results if row.kind == "fusion"]
    if fusion:
        lines += ["", "## Navigation fusion experiments (seeds 000, 002, 003 ch. 2, 004)", "",
                  "| experiment | ours | seed claim | s | report |", "|---|---|---|---|---|"]
        for row, r in fusion:
            if "error" in r:
                lines.append(f"| {row.name} | **failed**: {r['error']} | | | |")
            else:
                lines.append(f"| {row.name} | {r['headline']} | {r['seed_claim']} | {r['seconds']:.0f} | `{r['report']}` |")
    notes = [f"- **{row.name}**: {row.note}" for row, _ in results if row.note]
    if notes:
        lines += ["", "## Notes", "", *notes]
    lines += ["", "Reproduce: `vslam bench --suite configs/bench.yaml" + (f" --repeat {repeat}" if repeat > 1 else "") + "`.", ""]
    return "\n".join(lines)
