"""BENCHMARKS.md (and the README's results table) from the sidecar's entries; ``vslam bench --check``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any


from vslam.bench.checks import METRICS, MISS, OP_TEXT, PASS, Outcome, check_report, evaluate_row, fmt_value
from vslam.bench.checks import measured_on, readme_table, replace_between_markers, target_text, tol_text, verdict
from vslam.bench.kinds import TABLE_ORDER, table_function
from vslam.bench.kinds.run import stage_table
from vslam.bench.suite import OWN_TABLE_KINDS, BenchRow, BenchSuite, entries_by_name, load_sidecar, load_suite, sidecar_path
from vslam.bench.tables import fmt, md_failed_row, md_section
from vslam.errors import ConfigError


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
        ate = fmt(r.get("ate_rmse"), ".4f")
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
            f"| {row.name} | {tracked} | {fmt(path, '.2f')} | {ate} | {pct} | {r.get('align', '–')} | {rpe} | {r['fps']:.1f} | {r['ms_per_frame']:.1f} | "
            f"{r['peak_rss_mb']:.0f} | {det} | {row.target} |"
        )
    lines += stage_table(entries)
    for kind in TABLE_ORDER:
        lines += table_function(kind)([(row, e["result"]) for row, e in entries if row.kind == kind])
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
