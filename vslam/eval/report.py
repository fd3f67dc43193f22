"""Write an evaluation to disk: metrics.json, PNG plots, report.md and a self-contained report.html.

The HTML embeds its PNGs as base64 data URIs and its CSS inline, so the one
file can be mailed or attached to a CI run and still shows everything.
"""

from __future__ import annotations

import base64
import html
import json
import logging
from pathlib import Path
from typing import Any

from vslam.eval import plots
from vslam.eval.metrics import ErrorStats
from vslam.eval.result import EvalResult
from vslam.outputs import write_bytes, write_text

logger = logging.getLogger(__name__)

Table = tuple[str, list[str], list[list[str]]]  # (title, header, rows)

PLOTS: tuple[tuple[str, str, str], ...] = (
    ("trajectory", "trajectory.png", "Trajectories, top view (GT dashed, estimate coloured by ATE)"),
    ("ate_time", "ate_time.png", "ATE over time"),
    ("ate_hist", "ate_hist.png", "ATE histogram"),
    ("rpe_time", "rpe_time.png", "RPE translation over time"),
)

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:60rem;margin:2rem auto;padding:0 1rem;color:#222}
h1{font-size:1.6rem}h2{font-size:1.2rem;margin-top:2rem;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.5rem 0 1rem}th,td{border:1px solid #ccc;padding:.25rem .6rem;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
figure{margin:1rem 0}img{max-width:100%;border:1px solid #eee}figcaption{color:#555;font-size:.9rem}
ul.notes li{color:#7a4b00}
"""


def write_report(result: EvalResult, out_dir: str | Path, title: str = "Trajectory evaluation", *,
                 run: dict[str, Any] | None = None, maps: dict[int, EvalResult] | None = None) -> dict[str, Path]:
    """Write the report files; returns their paths by name.

    Keys: metrics (metrics.json), report_md, report_html, and one per plot drawn
    (trajectory, ate_time, ate_hist, rpe_time) when ``result.config.plots`` and
    the result still holds its per-pose arrays.

    run: the whole run (``RunResult.run_summary``: frames, posed, maps) when ``result`` scores one part of it;
    written to metrics.json as ``run`` and shown first, so a reader sees what the headline number covers.
    maps: each map's own evaluation when maps were never merged (metrics.json ``maps``, a plot per map).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    maps = maps or {}

    files["metrics"] = out / "metrics.json"
    metrics = result.to_dict()
    if run is not None:
        metrics["run"] = run
    if maps:
        metrics["maps"] = {str(m): e.to_dict() for m, e in sorted(maps.items())}
    write_text(files["metrics"], json.dumps(metrics, indent=2) + "\n")

    images: dict[str, bytes] = {}
    if result.config.plots and result.arrays is not None:
        images = _draw(result)
        for key, name, _ in PLOTS:
            if key in images:
                files[key] = out / name
                write_bytes(files[key], images[key])
    map_images: dict[int, bytes] = {}
    if result.config.plots and len(maps) > 1:
        for m, e in sorted(maps.items()):
            if e.arrays is not None:
                map_images[m] = plots.trajectory_png(e.arrays, e.alignment.method)
                files[f"trajectory_map{m}"] = out / f"trajectory_map{m}.png"
                write_bytes(files[f"trajectory_map{m}"], map_images[m])

    tables = run_tables(run) + report_tables(result, scope=_scope(run))
    files["report_md"] = out / "report.md"
    write_text(files["report_md"], _markdown(result, title, tables, [k for k, _, _ in PLOTS if k in images],
                                             sorted(map_images)))
    files["report_html"] = out / "report.html"
    write_text(files["report_html"], _html(result, title, tables, images, map_images))
    logger.info("wrote evaluation report to %s", out)
    return files


def _draw(result: EvalResult) -> dict[str, bytes]:
    assert result.arrays is not None
    images = {
        "trajectory": plots.trajectory_png(result.arrays, result.alignment.method),
        "ate_time": plots.ate_time_png(result),
        "ate_hist": plots.ate_hist_png(result),
    }
    rpe = plots.rpe_time_png(result)
    if rpe is not None:
        images["rpe_time"] = rpe
    return images


def _scope(run: dict[str, Any] | None) -> str:
    """What the headline evaluation covers, as its section titles say it."""
    if run is None or run.get("scored_map") is None:
        return ""
    poses = next(m["poses"] for m in run["maps"] if m["map"] == run["scored_map"])
    return f"largest map (map {run['scored_map']}, {poses} of {run['frames']} frames)"


def run_tables(run: dict[str, Any] | None) -> list[Table]:
    """The whole run (frames read, posed, tracked) and, with several maps, every map with its own ATE."""
    if run is None:
        return []
    n = run["frames"]
    rows = [["frames read", str(n)],
            ["posed", f"{run['posed']} of {n} ({100 * run['posed_fraction']:.1f} %)"],
            ["tracked (measured)", f"{run['tracked']} of {n}"],
            ["maps", str(len(run["maps"]))],
            ["scale", "metric" if run["metric_scale"] else "not observable (monocular): Sim3 alignment"],
            ["scored below", run["scored"]]]
    tables: list[Table] = [("Run", ["", ""], rows)]
    if len(run["maps"]) > 1:
        head = ["map", "poses", "tracked", "ATE rmse (m)", "alignment"]
        body = [[str(m["map"]), str(m["poses"]), str(m["tracked"]),
                 _f(m["ate_rmse"]) if "ate_rmse" in m else "not scored (too few poses matched the ground truth)",
                 (m["align"] + (f", scale {m['scale']:.4f}" if m["align"] == "sim3" else "")) if "align" in m else "–"]
                for m in run["maps"]]
        tables.append(("Maps (never merged; each aligned on its own)", head, body))
    return tables


def report_tables(result: EvalResult, scope: str = "") -> list[Table]:
    """The report's tables as strings, shared by the Markdown and HTML writers; ``scope`` names the part of the
    run they score when it is not the whole run."""
    r = result
    tu = "s" if r.time_unit == "s" else "frames"
    how = f"by timestamp within {r.config.max_diff:g} s" if r.matched_by == "time" else "line by line"
    al = r.alignment
    align = al.method + (f", scale {al.s:.6f}" if al.method == "sim3" else "")
    if r.config.align == "auto":
        align += f" (auto: {'scale not observable (monocular)' if r.monocular else 'metric scale'})"
    summary = [
        ["estimate", r.est_path or "(in memory)"],
        ["ground truth", r.gt_path or "(in memory)"],
        ["matched poses", f"{r.n_matched} of {r.n_est} estimated / {r.n_gt} GT, {how}"],
        ["duration", f"{r.duration:.2f} {tu}"],
        ["path length", f"GT {r.gt_length_m:.3f} m, estimate {r.est_length_m:.3f} m (aligned)"],
        ["alignment", align],
    ]
    stat_head = ["", "rmse", "mean", "median", "std", "min", "max", "n"]
    ate = [_stat_row("translation (m)", r.ate.translation), _stat_row("rotation (deg)", r.ate.rotation_deg)]
    rpe_head = ["delta", "trans rmse (m)", "trans mean (m)", "trans median (m)", "trans max (m)"]
    rpe_head += ["rot rmse (deg)", "rot mean (deg)", "rot max (deg)", "pairs"]
    rpe = []
    for s in r.rpe:
        t, q = s.translation, s.rotation_deg
        rpe.append([s.label, *map(_f, (t.rmse, t.mean, t.median, t.max, q.rmse, q.mean, q.max)), str(t.n)])
    of = f": {scope}" if scope else ""
    tables: list[Table] = [(f"Summary{of}", ["", ""], summary), (f"ATE (after alignment){of}", stat_head, ate)]
    if rpe:
        tables.append(("RPE", rpe_head, rpe))
    if r.kitti is not None:
        k = r.kitti
        rows = [[f"{p.length:g} m", f"{p.t_rel:.4f}", f"{p.r_rel:.4f}", str(p.n_segments)] for p in k.per_length]
        rows.append(["all", f"{k.t_rel:.4f}", f"{k.r_rel:.4f}", str(k.n_segments)])
        tables.append(("KITTI odometry metric (devkit, no alignment)", ["length", "t_rel (%)", "r_rel (deg/100 m)", "segments"], rows))
    return tables


def _stat_row(name: str, s: ErrorStats) -> list[str]:
    return [name, *(_f(v) for v in (s.rmse, s.mean, s.median, s.std, s.min, s.max)), str(s.n)]


def _f(v: float) -> str:
    return f"{v:.6f}"


def _markdown(result: EvalResult, title: str, tables: list[Table], plot_keys: list[str], map_plots: list[int]) -> str:
    lines = [f"# {title}", ""]
    for name, head, rows in tables:
        lines += [f"## {name}", ""]
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "|".join("---" for _ in head) + "|")
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
        lines.append("")
    if result.kitti is None:
        lines += ["## KITTI odometry metric", "", f"{result.kitti_reason}", ""]
    if result.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in result.notes] + [""]
    if plot_keys:
        lines += ["## Plots", ""]
        for key, name, caption in PLOTS:
            if key in plot_keys:
                lines += [f"![{caption}]({name})", ""]
    if map_plots:
        lines += ["## Each map", ""] + [f"![map {m}, aligned on its own](trajectory_map{m}.png)\n" for m in map_plots]
    return "\n".join(lines)


def _html(result: EvalResult, title: str, tables: list[Table], images: dict[str, bytes],
          map_images: dict[int, bytes]) -> str:
    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{e(title)}</h1>",
    ]
    for name, head, rows in tables:
        parts.append(f"<h2>{e(name)}</h2><table>")
        if any(head):
            parts.append("<tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>")
        parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>" for row in rows]
        parts.append("</table>")
    if result.kitti is None:
        parts.append(f"<h2>KITTI odometry metric</h2><p>{e(result.kitti_reason or '')}</p>")
    if result.notes:
        parts.append('<h2>Notes</h2><ul class="notes">' + "".join(f"<li>{e(n)}</li>" for n in result.notes) + "</ul>")
    if images:
        parts.append("<h2>Plots</h2>")
        for key, _, caption in PLOTS:
            if key in images:
                data = base64.b64encode(images[key]).decode("ascii")
                parts.append(
                    f'<figure><img alt="{e(caption)}" src="data:image/png;base64,{data}">'
                    f"<figcaption>{e(caption)}</figcaption></figure>"
                )
    if map_images:
        parts.append("<h2>Each map</h2>")
        for m, png in sorted(map_images.items()):
            data = base64.b64encode(png).decode("ascii")
            parts.append(f'<figure><img alt="map {m}" src="data:image/png;base64,{data}">'
                         f"<figcaption>map {m}, aligned to the ground truth on its own</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
