"""Kinds ``run`` (a pipeline run scored against ground truth; the main table) and ``synthetic_render``."""

from __future__ import annotations

import csv
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from vslam.bench.suite import PER_FRAME, STAGES, BenchRow
from vslam.bench.tables import fmt
from vslam.childproc import peak_rss_mb
from vslam.config import deep_merge, from_dict, load_yaml


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    return run_pipeline(config, overrides, out_dir)[0]


def run_pipeline(config: str | None, overrides: dict[str, Any], out_dir: str) -> tuple[dict[str, Any], Any]:
    """One pipeline run -> (the result row ``job`` keeps, the ``RunResult``: trajectory, ground truth, eval)."""
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
        if res.eval.alignment.method == "sim3":  # inertial: the fitted scale says how metric a mono(-inertial) run is
            row["align"] += f" (s={res.eval.alignment.s:.4f})"
        row["path_m"] = res.eval.gt_length_m
        first = res.eval.rpe[0] if res.eval.rpe else None
        if first is not None:
            row["rpe_t"] = first.translation.rmse
            row["rpe_r"] = first.rotation_deg.rmse
            row["rpe_delta"] = first.label
    # several maps: frames with no pose (between maps), maps started, and each map's own ATE when they never merged
    status = [str(r.get("status", "")) for r in res.stats]
    row["lost"] = status.count("lost")
    row["new_maps"] = status.count("new_map")
    row["merges"] = int(res.recovery.get("merges", 0))
    row["map_switches"] = int(res.recovery.get("map_switches", 0))
    merge_ms = [float(r["ms_map_merge"]) for r in res.stats if r.get("ms_map_merge") not in (None, "")]
    if merge_ms:  # keyframes looked for in the archived maps
        row["merge_query_ms"] = float(np.median(merge_ms))
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
    # long runs: does a frame cost more once the map is large? Medians of the first and last 500 frames
    totals = [float(r["ms_total"]) for r in res.stats if r.get("ms_total") not in (None, "")]
    if len(totals) >= 1000:
        row["ms_first500"], row["ms_last500"] = float(np.median(totals[:500])), float(np.median(totals[-500:]))
    row["peak_rss_mb"] = peak_rss_mb()
    return row, res


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


def job_render(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
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


def stage_table(entries: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Per-stage milliseconds (features, matching, pose, BA) of the rows whose runs wrote stats.csv."""
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
        cells = [fmt(st.get(c), ".1f") for c in cols]
        lines.append(f"| {row.name} | " + " | ".join(cells) + f" | {fmt(st.get('mapping_per_kf'), '.1f')} | "
                     f"{'–' if kfs is None else kfs} | {fmt(st.get('total'), '.1f')} |")
    return lines
