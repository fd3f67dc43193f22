"""`vslam bench`: run a suite of (config, sequence) rows and rewrite BENCHMARKS.md.

Each run happens in a fresh spawned process so its peak memory is its own
and one row cannot warm caches for the next. Timings are only compared as
ratios inside one BENCHMARKS.md (same machine, same run). ``--jobs N`` / ``--ray``
run the jobs in parallel (``vslam.batch``): the same metrics, timings no longer clean.
``--sweep KEY=V1,V2`` runs every selected row once per value (a parameter sweep).

The measured numbers live in a machine-readable sidecar next to the Markdown
(``BENCHMARKS.json`` beside ``BENCHMARKS.md``): ``--only NAME`` re-measures
those rows, keeps every other row from the sidecar and re-renders the whole
file, with the date each row was measured. Parsing the Markdown back would
break with every change of its layout; the JSON does not.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime as _dt
import json
import logging
import math
import multiprocessing as mp
import os
import platform
import shutil
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from vslam.bench_checks import METRICS, MISS, OP_TEXT, PASS, Check, Outcome, check_report, evaluate_row, fmt_value
from vslam.bench_checks import git_commit, measured_on, readme_table, replace_between_markers, target_text, tol_text
from vslam.bench_checks import verdict
from vslam.childproc import peak_rss_mb
from vslam.config import deep_merge, from_dict, load_yaml, parse_overrides
from vslam.errors import ConfigError
from vslam.progress import Progress

log = logging.getLogger(__name__)

SIDECAR_VERSION = 1
# stats.csv columns shown in the per-stage table, in pipeline order; other ms_* columns follow
STAGES = ("features", "depth", "pose", "mapping", "map_create", "map_fuse_cull", "map_ba", "map_wait", "map_loop")
PER_FRAME = ("features", "depth", "pose", "total")  # run on every frame: median ms/frame
# kinds run once whatever --repeat says (deterministic, or repeating their measurement inside the job)
SINGLE_RUN_KINDS = ("place", "features", "pose", "detector", "speed", "line_ba", "eval_detector")
# kinds with a table of their own below the SLAM table
OWN_TABLE_KINDS = ("fusion", "imu_preint", "batch", "ab") + SINGLE_RUN_KINDS

@dataclass(frozen=True)
class BenchRow:
    name: str
    kind: Literal["run", "synthetic_render", "fusion", "imu_preint", "batch", "place", "features", "pose", "detector",
                  "ab", "speed", "line_ba", "eval_detector"] = "run"
    config: str = ""  # pipeline YAML, relative to the suite file's folder's parent (the repo root) or absolute
    set: tuple[str, ...] = ()  # KEY=VALUE overrides
    note: str = ""
    target: str = ""  # the number the row must reach, in words (default: the checks written out)
    check: tuple[Check, ...] = ()  # the target as machine checks (vslam.bench_checks), verdicts computed from the sidecar
    headline: str = ""  # non-empty: a row of the README's results table, this its short "what it measures"
    experiment: str = ""  # kind "fusion": a key of vslam.fusion.experiments.EXPERIMENTS
    # kind "batch" (issue 10): the jobs are the grid's cartesian product of KEY: [values] on top of ``set``,
    # run serially, over a process pool and on a local Ray instance of ``workers`` each; wall times compared
    grid: dict[str, Any] = field(default_factory=dict)
    workers: int = 2
    # kind "ab": every grid point run without (A) and with (B) these KEY=VALUE overrides (``batch.ab_result``)
    treatment: tuple[str, ...] = ()
    # kind "run" on composited people (issue 5): {data: TUM folder under $VSLAM_DATA, people: 3, seed: 0,
    # coco: coco128}; ``vslam make-dynamic`` writes it once under <runs>/_data and dataset.path points there.
    # Kind "ab" takes seeds: [..] instead of seed: one composite (other walkers) per grid point
    make_dynamic: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class BenchSuite:
    title: str = "vslam benchmarks"
    rows: tuple[BenchRow, ...] = field(default_factory=tuple)


def _job_run(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.pipeline import Pipeline, PipelineConfig

    cfg = PipelineConfig.load(config, deep_merge(overrides, {"output": {"dir": out_dir}}))
    shutil.rmtree(out_dir, ignore_errors=True)  # the row's own folder: its previous run goes without a warning
    res = Pipeline(cfg).run()
    # frames: posed (trajectory lines); frames_read: every frame the run took, posed or not
    row: dict[str, Any] = {"frames": len(res.trajectory), "frames_read": res.n_frames, "tracked": int(res.tracked.sum()),
                           "fps": res.fps, "ms_per_frame": 1e3 * res.seconds / max(1, len(res.trajectory))}
    if res.eval is not None:
        row["ate_rmse"] = res.eval.ate.translation.rmse
        row["align"] = res.eval.alignment.method
        if res.eval.alignment.method == "sim3":  # issue 8: the fitted scale says how metric a mono(-inertial) run is
            row["align"] += f" (s={res.eval.alignment.s:.4f})"
        row["path_m"] = res.eval.gt_length_m
        first = res.eval.rpe[0] if res.eval.rpe else None
        if first is not None:
            row["rpe_t"] = first.translation.rmse
            row["rpe_r"] = first.rotation_deg.rmse
            row["rpe_delta"] = first.label
    # issue 38: frames with no pose (between maps), maps started, and each map's own ATE when they never merged
    status = [str(r.get("status", "")) for r in res.stats]
    row["lost"] = status.count("lost")
    row["new_maps"] = status.count("new_map")
    if res.eval is not None and 3 <= int(res.tracked.sum()) < len(res.trajectory) and not res.map_evals:
        # predicted frames carry no measurement: the same run scored on its measured frames alone, beside
        from vslam.eval import evaluate

        gt = res.eval_groundtruth
        if gt is not None:
            sub = res.trajectory.subset(np.flatnonzero(res.tracked))
            row["ate_rmse_measured"] = evaluate(sub, gt, res.eval.config, monocular=res.eval.monocular).ate.translation.rmse
    if res.map_evals:
        ids = res.map_ids if res.map_ids is not None else []
        row["maps"] = {str(m): {"frames": int(np.sum(ids == m)), "ate_rmse": e.ate.translation.rmse}
                       for m, e in sorted(res.map_evals.items())}
    row.update(stage_times(Path(out_dir) / "stats.csv"))
    # issue 41, long runs: does a frame cost more once the map is large? Medians of the first and last 500 frames
    totals = [float(r["ms_total"]) for r in res.stats if r.get("ms_total") not in (None, "")]
    if len(totals) >= 1000:
        row["ms_first500"], row["ms_last500"] = float(np.median(totals[:500])), float(np.median(totals[-500:]))
    row["peak_rss_mb"] = peak_rss_mb()
    return row


def stage_times(stats_csv: Path) -> dict[str, Any]:
    """Per-stage cost of one run from its stats.csv -> {"stages": {stage: ms}, "keyframes": K}.

    Stages that run on every frame (features, depth, pose, total) give their median ms/frame. Mapping
    runs on keyframes only, so its median per frame is 0: mapping and its sub-stages give the mean ms
    per frame (the amortised cost), and ``mapping_per_kf`` the median ms per keyframe (rows where a
    mapping sub-stage was timed). Empty when the file is missing.
    """
    if not stats_csv.is_file():
        return {}
    with open(stats_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    cols = [c[3:] for c in rows[0] if c.startswith("ms_")]

    def values(col: str, fill: float | None) -> list[float]:
        out = []
        for r in rows:
            v = r.get("ms_" + col, "")
            if v not in ("", None):
                out.append(float(v))
            elif fill is not None:
                out.append(fill)
        return out

    stages: dict[str, float] = {}
    for col in cols:
        if not values(col, None):
            continue  # never ran (e.g. loop closing off)
        if col in PER_FRAME:
            vals = values(col, None)
            if vals:
                stages[col] = statistics.median(vals)
        else:
            stages[col] = statistics.fmean(values(col, 0.0))  # blank = the stage did not run on that frame
    kf_col = next((c for c in cols if c.startswith("map_")), None)
    kf_rows = [r for r in rows if kf_col and r.get("ms_" + kf_col, "") != ""]
    if kf_rows and "mapping" in cols:
        stages["mapping_per_kf"] = statistics.median(float(r["ms_mapping"]) for r in kf_rows)
    return {"stages": stages, "keyframes": len(kf_rows)}


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
    return {"frames": n, "fps": n / dt, "ms_per_frame": 1e3 * dt / n, "peak_rss_mb": peak_rss_mb()}


def _job_fusion(experiment: str, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.fusion.experiments import EXPERIMENTS

    if experiment not in EXPERIMENTS:
        raise ConfigError(f"unknown fusion experiment {experiment!r}; known: {', '.join(sorted(EXPERIMENTS))}")
    t0 = time.perf_counter()
    m = EXPERIMENTS[experiment](Path(out_dir), seed=int(overrides.get("seed", 0)), quick=bool(overrides.get("quick", False)))
    return {"headline": m.get("headline", ""), "seed_claim": m.get("seed_claim", ""), "seconds": time.perf_counter() - t0,
            "report": str(Path(out_dir) / "report.md"), "peak_rss_mb": peak_rss_mb()}


def _job_imu_preint(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 8: real-IMU preintegration error/NEES from ground-truth states, and the static window (``set``:
    data=<folder under $VSLAM_DATA>, lengths=[...], static_window_s, noise_scale, align_spans=[...])."""
    from vslam.inertial.evaluate import evaluate_euroc_imu
    from vslam.paths import data_root

    t0 = time.perf_counter()
    out = evaluate_euroc_imu(data_root() / str(overrides.get("data", "euroc/V1_01_easy_micro")),
                             tuple(float(x) for x in overrides.get("lengths", (0.5, 1.0, 2.0))),
                             float(overrides.get("static_window_s", 4.0)), float(overrides.get("noise_scale", 1.0)),
                             tuple(float(x) for x in overrides.get("align_spans", (3.0, 5.0, 10.0))))
    return {**out, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def _job_place(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 7: recall@1/5/10 of the place descriptors (``set``: descriptors=[bow, vladnet], weights=<file>,
    seed=<held-out synthetic route>, tum=<folder under $VSLAM_DATA>) and the keyframe database's cost at 10k."""
    from vslam.loop.descriptor import default_vladnet_path
    from vslam.loop.retrieval import bow_describer, database_costs, evaluate_held_out, held_out_sets, vladnet_describer
    from vslam.paths import data_root

    t0 = time.perf_counter()
    names = [str(n) for n in overrides.get("descriptors", ("bow", "vladnet"))]
    make = {"bow": bow_describer, "vladnet": lambda: vladnet_describer(str(overrides.get("weights") or default_vladnet_path()))}
    desc = {n: make[n]() for n in names}
    held = held_out_sets(int(overrides.get("seed", 0)), int(overrides.get("frames", 600)), stride=int(overrides.get("stride", 3)),
                         tum=data_root() / str(overrides.get("tum", "tum/rgbd_dataset_freiburg3_teddy")),
                         tum_split=int(overrides.get("tum_split", 100)))
    sets = {held[k].label: r for k, r in evaluate_held_out(desc, held).items()}
    dims = {n: next(iter(sets.values()))[n]["dim"] for n in names}
    return {"sets": sets, "costs": {n: database_costs(d) for n, d in dims.items()}, "seconds": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb()}


def _job_features(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 4: ConvPoint vs ORB vs SIFT on the same held-out pairs (``set``: keypoints, pairs, images, seed,
    weights=<file>; ``features.evaluate``)."""
    import torch

    from vslam.features.convpoint import default_weights
    from vslam.features.evaluate import FeatureBenchConfig, run_feature_bench
    from vslam.paths import data_root

    torch.set_num_threads(2)
    t0 = time.perf_counter()
    cfg = FeatureBenchConfig(n_keypoints=int(overrides.get("keypoints", 1000)), pairs_per_image=int(overrides.get("pairs", 2)),
                             max_images_per_source=int(overrides.get("images", 12)), seed=int(overrides.get("seed", 0)))
    res = run_feature_bench(str(overrides.get("weights") or default_weights()), data_root(), cfg)
    return {**res, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def _job_pose(overrides: dict[str, Any]) -> dict[str, Any]:
    """Two-view relative pose AUC of keypoint methods on real pairs with ground truth (``set``: methods=[names],
    keypoints, pairs, threads; ``features.pose_auc``)."""
    import torch

    from vslam.features.pose_auc import PoseBenchConfig, pose_benchmark, standard_methods
    from vslam.paths import data_root

    threads = int(overrides.get("threads", 2))
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    cfg = PoseBenchConfig(n_keypoints=int(overrides.get("keypoints", 2000)), pairs=int(overrides.get("pairs", 50)))
    names = tuple(str(m) for m in overrides.get("methods", ["orb", "sift", "alike-t"]))
    res = pose_benchmark(standard_methods(cfg.n_keypoints, names), data_root(), cfg)
    return {**res, "threads": threads, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def _job_detector(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 5: the attention ablation (``set``: weights=[files], all trained with one recipe; ``dynamic.evaluate``)."""
    from vslam.dynamic.evaluate import evaluate_detectors

    t0 = time.perf_counter()
    weights = [str(w) for w in overrides.get("weights", ())]
    if not weights:
        raise ConfigError("bench kind detector needs set: weights=[file, ...]")
    res = evaluate_detectors(weights, threads=int(overrides.get("threads", 2)))
    return {**res, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def _job_eval_detector(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 40: ``vslam eval-detector`` over several labelled folders. ``set``: data=[folder:split, ...] (under
    $VSLAM_DATA), model (checkpoint; "" = the shipped one) or teacher=true (FastestDet), img_size, threads ->
    {"sets": {"<folder's first part>-<split>": the evaluator's report}}."""
    from vslam.dynamic.eval_detector import build_detector, evaluate, predict
    from vslam.dynamic.datasets import load_records
    from vslam.paths import data_root

    t0 = time.perf_counter()
    data = [str(d) for d in overrides.get("data", ())]
    if not data:
        raise ConfigError("bench kind eval_detector needs set: data=[folder:split, ...]")
    det, threshold, name = build_detector(str(overrides.get("model", "")), bool(overrides.get("teacher", False)),
                                          int(overrides.get("threads", 2)), int(overrides.get("img_size", 0)),
                                          bool(overrides.get("wide", False)))
    sets = {}
    for spec in data:
        folder, _, split = spec.partition(":")
        _, records = load_records(data_root() / folder, split or "val")  # type: ignore[arg-type]
        rep = evaluate(records, predict(det, records), threshold)
        sets[f"{Path(folder).parts[0]}-{split or 'val'}"] = rep
    return {"model": name, "threshold": threshold, "sets": sets, "seconds": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb()}


def _job_speed(overrides: dict[str, Any]) -> dict[str, Any]:
    """Issue 10: the learned front end's networks, ms per frame on one device (``profiling.network_speed``;
    ``set``: device, frames, repeats, threads). device=cuda on a machine without a GPU is skipped, not failed:
    the row keeps what a GPU machine measured."""
    import torch

    from vslam.profiling import network_speed

    device = str(overrides.get("device", "auto"))
    if device == "cuda" and not torch.cuda.is_available():
        return {"skipped": "no CUDA device here"}
    return network_speed(device, frames=int(overrides.get("frames", 20)), repeats=int(overrides.get("repeats", 3)),
                         threads=int(overrides.get("threads", 2)))


def execute_job(kind: str, config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """One job in this process -> its result row (``vslam.batch`` calls this in its worker processes)."""
    if kind == "fusion":
        return _job_fusion(str(config), overrides, out_dir)
    if kind == "imu_preint":
        return _job_imu_preint(overrides)
    if kind == "place":
        return _job_place(overrides)
    if kind == "features":
        return _job_features(overrides)
    if kind == "pose":
        return _job_pose(overrides)
    if kind == "detector":
        return _job_detector(overrides)
    if kind == "eval_detector":
        return _job_eval_detector(overrides)
    if kind == "speed":
        return _job_speed(overrides)
    if kind == "line_ba":
        from vslam.profiling import line_ba_cost

        return line_ba_cost(config, overrides, out_dir)
    fn = _job_run if kind == "run" else _job_render
    return fn(config, overrides, out_dir)


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
    stage_runs = [r["stages"] for r in ok if r.get("stages")]
    if stage_runs:
        names = list(dict.fromkeys(k for st in stage_runs for k in st))
        agg["stages"] = {k: statistics.median(st[k] for st in stage_runs if k in st) for k in names}
    agg["n_runs"] = len(ok)
    agg["identical"] = len({round(r.get("ate_rmse", 0.0), 12) for r in ok}) == 1
    return agg


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


def _json_safe(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if hasattr(v, "item"):  # numpy scalar
        return _json_safe(v.item())
    return v


def run_bench(suite_path: str | Path, output: Path, repeat: int = 1, only: list[str] | None = None,
              jobs_dir: Path = Path("runs/bench"), workers: int = 1, ray: str | None = None,
              sweep: dict[str, list[Any]] | None = None, readme: Path | None = None,
              progress: Progress | None = None) -> Path:
    """Run the suite's rows (or those named in ``only``), merge with the rows kept in the sidecar
    ``output.with_suffix('.json')`` and rewrite ``output`` with every row of the suite measured so far.

    workers > 1 / ray: the jobs of all rows go out together (``vslam.batch.run_jobs``). sweep {KEY: [values]}:
    each selected row once per value, as rows ``NAME[KEY=V]`` of a suite of their own (nothing kept). readme: also
    rewrite that file's results table of headline rows (``write_readme_table``; not for a sweep). progress(done,
    total): jobs ended, of all the jobs the rows run."""
    from vslam.batch import Job, ab_jobs, ab_result, batch_row, run_jobs

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
            kept[row.name] = {"result": _json_safe(result), "measured": now, "repeat": 1, "machine": machine, **commit}
        elif row.kind == "fusion":  # one seeded, deterministic run: repeating it only costs time
            plan.append((row, [Job("fusion", row.experiment, over, str(jobs_dir / row.name))]))
        elif row.kind == "ab":  # A and B on every grid point, in the same pool as the other rows
            plan.append((row, ab_jobs(cfg, over, grid, parse_overrides(list(row.treatment)), str(jobs_dir / row.name))))
            ab_labels[row.name] = labels
        else:  # a place / features row is deterministic and reports no timing that repeats would steady
            n = 1 if row.kind in SINGLE_RUN_KINDS else max(1, repeat)
            plan.append((row, [Job(row.kind, cfg, over, str(jobs_dir / f"{row.name}-{i}")) for i in range(n)]))
    results = iter(run_jobs([j for _, jobs in plan for j in jobs], workers, ray, progress))
    parallel = {"parallel": workers if ray is None else f"ray:{workers}"} if workers > 1 or ray is not None else {}
    for row, jobs in plan:
        done = [next(results) for _ in jobs]
        result = ab_result(ab_labels[row.name], done) if row.kind == "ab" else _aggregate(done)
        if "skipped" in result and row.name in kept:  # e.g. a GPU row on a machine without one
            log.info("%s: %s; its earlier measurement stays", row.name, result["skipped"])
            continue
        kept[row.name] = {"result": _json_safe(result), "measured": now, "repeat": 1 if row.kind == "ab" else len(jobs),
                          "machine": machine, **parallel, **commit}
    dropped = sorted(set(kept) - names)
    if dropped:
        log.info("%s: rows no longer in the suite dropped: %s", side, ", ".join(dropped))
    entries = [(r, kept[r.name]) for r in suite.rows if r.name in kept]
    side.parent.mkdir(parents=True, exist_ok=True)
    side.write_text(json.dumps({"version": SIDECAR_VERSION, "suite": str(suite_path), "written": now, "machine": machine,
                                "rows": {r.name: e for r, e in entries}}, indent=1, default=float) + "\n")
    output.write_text(render_markdown(suite, entries, now, machine))
    if readme is not None and not sweep:
        write_readme_table(suite, entries_by_name(entries), readme)
    return output


def entries_by_name(entries: list[tuple[BenchRow, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    return {row.name: e for row, e in entries}


def _sidecar_header(path: Path, kept: dict[str, dict[str, Any]]) -> tuple[str, str]:
    """(written, machine) of the bench run that last wrote the sidecar: its own fields, else its newest row's."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = {}
    if data.get("written") and data.get("machine"):
        return str(data["written"]), str(data["machine"])
    newest = max(kept.values(), key=lambda e: str(e.get("measured", "")), default={})
    return str(newest.get("measured", "–")), str(newest.get("machine", "–"))


def render_bench(suite_path: str | Path, output: Path, readme: Path | None = None) -> Path:
    """Rewrite ``output`` (and the README's results table) from the sidecar as it is: no job runs."""
    suite = load_suite(suite_path)
    side = sidecar_path(output)
    kept = load_sidecar(side)
    if not kept:
        raise ConfigError(f"{side}: no measured rows to render")
    now, machine = _sidecar_header(side, kept)
    entries = [(r, kept[r.name]) for r in suite.rows if r.name in kept]
    output.write_text(render_markdown(suite, entries, now, machine))
    if readme is not None:
        write_readme_table(suite, kept, readme)
    return output


def check_bench(suite_path: str | Path, output: Path) -> tuple[list[str], int]:
    """``vslam bench --check``: the suite's checks on the sidecar of ``output`` as written -> (lines, exit code)."""
    suite = load_suite(suite_path)
    return check_report(list(suite.rows), load_sidecar(sidecar_path(output)))


def write_readme_table(suite: BenchSuite, entries: dict[str, dict[str, Any]], readme: Path) -> bool:
    """The headline rows' table between the README's bench-table markers (a warning, no write, without them)."""
    return replace_between_markers(readme, readme_table(list(suite.rows), entries))


def _composited(spec: dict[str, Any], jobs_dir: Path) -> tuple[str, Path]:
    """(dataset kind, folder) of the make-dynamic sequence a row names, written on first use (seeded: the same
    spec, the same frames)."""
    from vslam.data.kitti import is_kitti_layout
    from vslam.dynamic.composite import make_dynamic, walker_config
    from vslam.paths import data_root

    unknown = set(spec) - {"data", "people", "seed", "coco"}
    if unknown or "data" not in spec:
        raise ConfigError(f"make_dynamic: needs 'data' and takes people, seed (seeds: kind ab), coco; got {sorted(spec)}")
    src = data_root() / str(spec["data"])
    cfg = walker_config(src, int(spec["people"]) if "people" in spec else None, int(spec.get("seed", 0)))
    kitti = is_kitti_layout(src)
    out = (jobs_dir / "_data" / f"{src.name}-people{cfg.n_people}-seed{cfg.seed}").resolve()
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
    from vslam.batch import grid_sets

    points = grid_sets(sweep)
    out = [dataclasses.replace(row, name=f"{row.name}[{','.join(sets)}]", set=row.set + sets)
           for row in rows if row.kind in ("run", "synthetic_render") for sets in points]
    if not out:
        raise ConfigError("--sweep: none of the selected rows is a pipeline run")
    return out


def _measured_lines(entries: list[tuple[BenchRow, dict[str, Any]]], machine: str) -> list[str]:
    """One line per (date, repeat, machine) group: which rows were measured when."""
    groups: dict[tuple[str, int, str, str], list[str]] = {}
    for row, e in entries:
        groups.setdefault((e["measured"], int(e["repeat"]), e.get("machine", ""), str(e.get("parallel", ""))), []).append(row.name)
    lines = []
    for (when, rep, mach, par), names in sorted(groups.items(), reverse=True):
        other = f" on {mach}" if mach and mach != machine else ""
        par = f", {par} jobs at a time (timings share the cores)" if par else ""
        lines.append(f"- {when}, {rep} run(s) per row{other}{par}: {', '.join(names)}")
    return lines


def render_markdown(suite: BenchSuite, entries: list[tuple[BenchRow, dict[str, Any]]], now: str, machine: str) -> str:
    """The whole BENCHMARKS.md from sidecar entries ({"result", "measured", "repeat", "machine", "commit"})."""
    from vslam.batch import ab_table, batch_table

    targets = _targets_table(entries)
    entries = [(dataclasses.replace(row, target=_target_cell(row, entries_by_name(entries))), e) for row, e in entries]
    lines = [
        f"# {suite.title}",
        "",
        f"Written by `vslam bench` on {now}.",
        f"Machine: {machine}.",
        "Each row: its run(s) in a fresh process; numbers are medians, ± is max−min over the runs.",
        "Timings are comparable only between rows measured together (same machine, same session). Measured:",
        "",
        *_measured_lines(entries, machine),
        "",
        "| row | frames (tracked) | path m | ATE RMSE m | ATE % of path | align | RPE trans / rot | frames/s | ms/frame | peak RSS MB | deterministic | target |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row, e in entries:
        r, repeat = e["result"], int(e["repeat"])
        if row.kind in OWN_TABLE_KINDS:
            continue
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 12))
            continue
        ate = _fmt(r.get("ate_rmse"), ".4f")
        if r.get("ate_rmse_spread") and repeat > 1:
            ate += f" ± {r['ate_rmse_spread']:.4f}"
        if r.get("ate_rmse_measured") is not None:
            ate += f" (measured frames: {r['ate_rmse_measured']:.4f})"
        if r.get("maps"):  # maps never merged: the headline is the one with most frames, then each on its own
            ate += f" ({len(r['maps'])} maps: " + ", ".join(
                f"{m['frames']} fr {m['ate_rmse']:.4f}" for m in r["maps"].values()) + ")"
        rpe = "–" if r.get("rpe_t") is None else f"{r['rpe_t']:.4f} m / {r['rpe_r']:.3f}° per {r['rpe_delta']}"
        tracked = f"{r['frames']} ({r['tracked']})" if "tracked" in r else f"{r['frames']}"
        if r.get("new_maps") or r.get("lost"):
            tracked += f", {r.get('new_maps', 0)} new map(s), {r.get('lost', 0)} lost"
        det = ("yes" if r.get("identical") else "**no**") if repeat > 1 and "ate_rmse" in r else "–"
        path = r.get("path_m")
        pct = "–" if path is None or r.get("ate_rmse") is None or path <= 0 else f"{100 * r['ate_rmse'] / path:.2f}"
        lines.append(
            f"| {row.name} | {tracked} | {_fmt(path, '.2f')} | {ate} | {pct} | {r.get('align', '–')} | {rpe} | {r['fps']:.1f} | {r['ms_per_frame']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {det} | {row.target} |"
        )
    lines += _stage_table(entries)
    fusion = [(row, e["result"]) for row, e in entries if row.kind == "fusion"]
    if fusion:
        lines += ["", "## Navigation fusion experiments (seeds 000, 002, 003 ch. 2, 004)", "",
                  "| experiment | ours | seed claim | s | report |", "|---|---|---|---|---|"]
        for row, r in fusion:
            if "error" in r:
                lines.append(f"| {row.name} | **failed**: {r['error']} | | | |")
            else:
                lines.append(f"| {row.name} | {r['headline']} | {r['seed_claim']} | {r['seconds']:.0f} | `{r['report']}` |")
    lines += _imu_table([(row, e["result"]) for row, e in entries if row.kind == "imu_preint"])
    lines += _place_table([(row, e["result"]) for row, e in entries if row.kind == "place"])
    lines += _features_table([(row, e["result"]) for row, e in entries if row.kind == "features"])
    lines += _pose_table([(row, e["result"]) for row, e in entries if row.kind == "pose"])
    lines += _detector_table([(row, e["result"]) for row, e in entries if row.kind == "detector"])
    lines += _eval_detector_table([(row, e["result"]) for row, e in entries if row.kind == "eval_detector"])
    lines += _speed_table([(row, e["result"]) for row, e in entries if row.kind == "speed"])
    lines += _line_ba_table([(row, e["result"]) for row, e in entries if row.kind == "line_ba"])
    lines += batch_table([(row, e["result"]) for row, e in entries if row.kind == "batch"])
    lines += ab_table([(row, e["result"]) for row, e in entries if row.kind == "ab"])
    lines += targets
    notes = [f"- **{row.name}**: {row.note}" for row, _ in entries if row.note]
    if notes:
        lines += ["", "## Notes", "", *notes]
    repeats = {int(e["repeat"]) for row, e in entries if row.kind not in ("fusion", "batch")}
    rep = max(repeats) if repeats else 1
    lines += ["", "Reproduce: `vslam bench --suite configs/bench.yaml" + (f" --repeat {rep}" if rep > 1 else "") +
              "` (one row: `--only NAME`; the other rows are kept from BENCHMARKS.json).", ""]
    return "\n".join(lines)


def _target_cell(row: BenchRow, entries: dict[str, dict[str, Any]]) -> str:
    """A table's target cell: the row's verdict, then its target (no mark for a target with no check)."""
    text = target_text(row)
    mark = verdict(evaluate_row(row, entries)) if row.check else ""
    return f"{mark} {text}".strip()


def _targets_table(entries: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Every row with a target: each check as measured vs its bound, the verdict, and what it was measured on."""
    rows = [(row, e) for row, e in entries if row.target or row.check]
    if not rows:
        return []
    by_name = entries_by_name(entries)
    lines = md_section("Targets", "Each row's checks (configs/bench.yaml `check:`) evaluated on the tables above: "
                       "✓ every check met, ✗ one missed, ✗ (open) only known misses (each says why: what is "
                       "missing, or that the row needs re-measuring), – a target in words only. `vslam bench --check` fails on a miss that is not open. Commit: the code the row "
                       "was measured with (– before commits were recorded).",
                       ["row", "target", "measured", "✓/✗", "measured (date, commit)"])
    for row, e in rows:
        outs = evaluate_row(row, by_name)
        got = "; ".join(_measured_cell(o) for o in outs) or "–"
        lines.append(f"| {row.name} | {target_text(row)} | {got} | {verdict(outs)} | {measured_on(e)} |")
    return lines


def _measured_cell(o: Outcome) -> str:
    """``ATE 0.0041 m (≤ 0.0045 m) ✓`` for one check."""
    label = METRICS[o.check.metric].label if o.check.metric in METRICS else o.check.metric
    got = fmt_value(o.check.metric, o.measured) if o.measured is not None else (o.why or "–")
    bound = "" if o.bound is None else f" ({OP_TEXT[o.check.op]} {fmt_value(o.check.metric, o.bound)}{tol_text(o.check)})"
    mark = {"pass": PASS, "fixed": PASS, "miss": MISS, "known": f"{MISS} open: {o.check.open}"}.get(o.status, "–")
    return f"{label} {got}{bound} {mark}"


def md_section(title: str, intro: str, columns: list[str]) -> list[str]:
    """Lines opening a BENCHMARKS.md section: ``## title``, an intro paragraph, a table head of ``columns``."""
    return ["", f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]


def md_failed_row(row: BenchRow, error: str, n_columns: int) -> str:
    """A table line for a row whose job failed: name, the error, empty cells, the target in the last column."""
    return f"| {row.name} | **failed**: {error} |" + " |" * (n_columns - 3) + f" {row.target} |"


def _imu_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 8 real-IMU numbers: one line per window length, then the static-window line per row."""
    if not rows:
        return []
    lines = md_section("IMU preintegration on real data",
                       "Windows start at ground-truth states (pose, velocity, biases); error of the predicted end pose; "
                       "NEES of rotation + position against the pim's covariance (6 dof: consistent ≈ 6).",
                       ["row", "window s", "windows", "position RMSE m", "rotation RMSE °", "predicted σ_p m",
                        "NEES mean (median)", "NEES rot / pos", "noise × for NEES 6", "target"])
    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 10))
            continue
        for w in r["windows"]:
            lines.append(f"| {row.name} | {w['length_s']:g} | {w['windows']} | {w['pos_rmse_m']:.4f} | {w['rot_rmse_deg']:.3f} "
                         f"| {w['sigma_pos_median_m']:.4f} | {w['nees_mean']:.0f} ({w['nees_median']:.0f}) "
                         f"| {w['nees_rot_mean']:.0f} / {w['nees_pos_mean']:.0f} | {w['noise_inflation_for_consistency']:.1f} | {row.target} |")
    ident = [(row, r) for row, r in rows if "error" not in r and r.get("identified")]
    if ident:
        lines += ["", "The same windows with an identified noise model (`vslam.inertial.evaluate.fit_noise_model`): white-noise "
                  "densities plus the std of the ground-truth biases' own error, fitted by maximum likelihood on the windows "
                  "of all three lengths that start in the first half of the flight; NEES on the second half (held out). "
                  "Last column: the same fit with the densities only (inflation as VINS-Mono / OKVIS do, no bias term).", "",
                  "| row | gyro density (× sensor.yaml) | accel density (×) | σ of GT gyro / accel bias | window s "
                  "| held-out windows | NEES mean (median) | NEES rot / pos | share < χ²₆ 95 % | densities-only fit: NEES |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for row, r in ident:
            d, m = r["identified"], r["identified"]["model"]
            for w in d["held_out"]:
                lines.append(f"| {row.name} | {m['gyro_noise_density']:.2e} ({d['gyro_density_x_datasheet']:.1f}) "
                             f"| {m['accel_noise_density']:.2e} ({d['accel_density_x_datasheet']:.1f}) "
                             f"| {m['gyro_bias_sigma']:.1e} rad/s / {m['accel_bias_sigma']:.3f} m/s² | {w['length_s']:g} "
                             f"| {w['windows']} | {w['nees_mean']:.1f} ({w['nees_median']:.1f}) "
                             f"| {w['nees_rot_mean']:.1f} / {w['nees_pos_mean']:.1f} | {100 * w['frac_nees_below_chi2_95']:.0f} % "
                             f"| {w['nees_mean_white_only']:.1f} |")
    for row, r in rows:
        if "error" not in r:
            st = r["static"]
            lines.append("")
            lines.append(f"{row.name}, static window {st['window_s']:g} s (still: {'yes' if st['still'] else 'no'}): gravity "
                         f"direction {st['gravity_dir_err_deg']:.2f}° from ground truth ({st['gravity_dir_err_gt_accel_bias_deg']:.2f}° "
                         f"with the ground-truth accel bias as prior); gyro bias error {st['gyro_bias_err_rad_s']:.4f} rad/s "
                         f"(ground-truth bias {st['gyro_bias_gt_norm_rad_s']:.4f} rad/s).")
    aligned = [(row, r) for row, r in rows if "error" not in r and r.get("alignment")]
    if aligned:
        lines += ["", "Visual-inertial alignment (`vi_align`) on ground-truth camera poses hidden behind a similarity "
                  "(scale 3.7, tilted frame), keyframes every 0.25 s, zero starting biases:", "",
                  "| row | span s | windows | scale error % median / max | gravity error ° median / max | gyro bias error rad/s |",
                  "|---|---|---|---|---|---|"]
        for row, r in aligned:
            for a in r["alignment"]:
                lines.append(f"| {row.name} | {a['span_s']:g} | {a['windows']} | {a['scale_err_median_pct']:.2f} / "
                             f"{a['scale_err_max_pct']:.2f} | {a['gravity_err_median_deg']:.2f} / {a['gravity_err_max_deg']:.2f} "
                             f"| {a['gyro_bias_err_median_rad_s']:.4f} |")
    return lines


def _place_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 7 retrieval: recall@k per evaluation set and descriptor, then the database cost at 10k keyframes."""
    if not rows:
        return []
    lines = md_section("Place recognition",
                       "A query counts when the database holds a frame of the same place; recalled at k when one of its k "
                       "most similar database frames is one. BoW: tf-idf of 512 ORB words on the tracker's keypoints (full "
                       "image); VLADNet: vslam/models/vladnet_v1.pt on the image (its model card says what it was trained on: not "
                       "these sets).",
                       ["row", "set", "descriptor", "queries", "R@1", "R@5", "R@10", "ms / image", "target"])
    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 9))
            continue
        for set_name, res in r["sets"].items():
            for d, m in res.items():
                lines.append(f"| {row.name} | {set_name} | {d} | {m['queries']} | {m['r@1']:.2f} | {m['r@5']:.2f} "
                             f"| {m['r@10']:.2f} | {m['ms_per_image']:.1f} | {row.target} |")
    lines += ["", "| row | descriptor | bytes per keyframe | query over 10k keyframes ms |", "|---|---|---|---|"]
    for row, r in rows:
        for d, c in r.get("costs", {}).items():
            lines.append(f"| {row.name} | {d} | {c['bytes_per_keyframe']} | {c['query_ms']:.2f} |")
    return lines


def _report_tables(rows: list[tuple[BenchRow, dict[str, Any]]], heading: str, format_table: Any) -> list[str]:
    """One section per row: ``heading`` (with the row's name), the row's own table, its target."""
    lines = []
    for row, r in rows:
        lines += ["", heading.format(name=row.name), ""]
        if "error" in r:
            lines.append(f"**failed**: {r['error']}")
            continue
        lines += [*format_table(r), "", f"Target: {row.target}"]
    return lines


def _features_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 4: the homography benchmark and epipolar inliers, ConvPoint vs ORB vs SIFT in one run."""
    from vslam.features.evaluate import format_table

    return _report_tables(rows, "## Keypoints: ConvPoint vs ORB vs SIFT (`{name}`)", format_table)


def _pose_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Two-view pose AUC at 5/10/20 degrees per pair set and extraction ms per frame, methods of one run."""
    from vslam.features.pose_auc import format_table

    return _report_tables(rows, "## Keypoints: two-view pose AUC (`{name}`)", format_table)


def _detector_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 5: detectors on the held-out sets (the attention ablation: one recipe, one seed)."""
    from vslam.dynamic.evaluate import format_table

    return _report_tables(rows, "## Dynamic-object detector (`{name}`)", format_table)


def _eval_detector_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 40: a detector on the real validation splits (``vslam eval-detector``), one table per folder."""
    from vslam.dynamic.eval_detector import format_report

    def tables(r: dict[str, Any]) -> list[str]:
        out = [f"{r['model']}, recall / precision / mask IoU at score {r['threshold']:g}"]
        for name, rep in r["sets"].items():
            out += ["", f"{name} ({rep['images']} images):", "", *format_report(rep, name)]
        return out

    return _report_tables(rows, "## Detector on real photos (`{name}`)", tables)


def _speed_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 10: the learned front end's networks per device, one table for all such rows."""
    from vslam.profiling import format_speed

    if not rows:
        return []
    done = [(row.name, r) for row, r in rows if "ms" in r]
    lines = ["", "## Learned front end, ms per 640x480 frame by device", "",
             "ConvPoint keypoints, the detector's mask step (detect + keypoints in boxes), LSD lines (CPU), VLADNet "
             "(per keyframe); front_end = the first three as the SLAM front-end thread runs them (in a row on the CPU; "
             "on CUDA LSD runs on a thread beside the networks). Medians over TUM teddy frames.", ""]
    lines += format_speed(done) if done else []
    for row, r in rows:
        if "ms" not in r:
            lines.append(f"- {row.name}: {r.get('error') or r.get('skipped')}")
    targets = sorted({row.target for row, _ in rows if row.target})
    return lines + ["", *(f"Target: {t}" for t in targets)]


def _line_ba_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Issue 6: back-end CPU of lines, each local BA solved without and with its lines (``profiling.line_ba_cost``)."""
    if not rows:
        return []
    lines = md_section("Back-end cost of lines (`line_ba`)",
                       "A SLAM run with lines in which every local BA that has lines is solved twice on the same window: "
                       "without its lines, then with them (the run goes on with the latter). CPU ms of the solving thread "
                       "per BA, and the ratio of the sums; free of the load and keyframe differences between two runs.",
                       ["row", "local BAs", "CPU ms per BA, points only", "with lines", "ratio", "ATE m (with lines)", "target"])
    for row, r in rows:
        if "error" in r or not r.get("bas"):
            lines.append(md_failed_row(row, r.get("error", "no local BA with lines"), 7))
            continue
        lines.append(f"| {row.name} | {r['bas']} | {r['points_ms']:.1f} | {r['lines_ms']:.1f} | **{r['ratio']:.2f}x** | "
                     f"{_fmt(r.get('ate_rmse'), '.4f')} | {row.target} |")
    return lines


def _stage_table(entries: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Per-stage milliseconds (issue 3: features, matching, pose, BA) of the rows whose runs wrote stats.csv."""
    timed = [(row, e["result"]["stages"], e["result"].get("keyframes")) for row, e in entries
             if row.kind == "run" and "error" not in e["result"] and e["result"].get("stages")]
    if not timed:
        return []
    seen = list(dict.fromkeys(k for _, st, _ in timed for k in st))
    cols = [c for c in STAGES if c in seen] + [c for c in seen if c not in STAGES and c not in ("total", "mapping_per_kf")]
    head = [c.replace("map_", "map: ") for c in cols]
    lines = ["", "## Time per stage (ms)", "",
             "features, depth (stereo matching / depth lookup), pose (projection matching + PnP + pose-only refinement) "
             "and total: median ms per frame. Mapping and its sub-stages (point creation, fusion + culling, local BA) "
             "run on keyframes only: mean ms per frame (amortised), and median ms per keyframe.", "",
             "| row | " + " | ".join(head) + " | mapping ms/keyframe | keyframes | total |",
             "|---|" + "---|" * (len(cols) + 3)]
    for row, st, kfs in timed:
        cells = [_fmt(st.get(c), ".1f") for c in cols]
        lines.append(f"| {row.name} | " + " | ".join(cells) + f" | {_fmt(st.get('mapping_per_kf'), '.1f')} | "
                     f"{'–' if kfs is None else kfs} | {_fmt(st.get('total'), '.1f')} |")
    return lines
