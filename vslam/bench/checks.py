"""Bench targets as machine checks: evaluated on BENCHMARKS.json as written, no runs.

A row of ``configs/bench.yaml`` carries ``check:``, a list of comparisons of one number of its result
(``BENCHMARKS.json`` ``rows.NAME.result``) with a value, or with a ratio (``ratio``, default 1) of another
row's number (``of``) plus an offset (``plus``), or of another number of the same row (``of_metric``)::

    check:
      - {metric: ate_rmse, op: "<=", value: 0.010}
      - {metric: ate_rmse, op: "<=", ratio: 1.1, of: tum-teddy-rgbd}
      - {metric: ms_per_frame, op: "<=", value: 22, open: "speed target not met yet on 2 CPU cores"}
      - {metric: ate_rmse, op: "~=", of: tum-teddy-rgbd, tol: 0.1}

``~=`` is "the same number within a relative ``tol``" (|measured - bound| <= tol x |bound|): rows that must give
the same poses as another, where exact equality would also flip when the two rows were measured apart, on
another machine or with other library versions (a chaotic run amplifies their last bits).

``metric`` is a derived metric of ``METRICS`` (``ate_pct_path``, ``untracked``, ``sim3_scale``, ...) or a
dotted path into the result dict (``ms.front_end``, ``stages.mapping_per_kf``); a path step may be a list
index or the unique prefix of a key (``sets.TUM.vladnet.r@1``). ``open`` marks a known miss and says why
(what is missing, in words a user reads): ``vslam bench --check`` lists such misses apart and fails only on the others.

Pure functions of (row, sidecar entries): ``vslam.bench.render`` renders and checks with them.
"""

from __future__ import annotations

import logging
import math
import re
import statistics
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

from vslam.errors import ConfigError

log = logging.getLogger(__name__)

OPS: dict[str, Callable[[float, float], bool]] = {
    "<=": lambda a, b: a <= b, "<": lambda a, b: a < b, ">=": lambda a, b: a >= b, ">": lambda a, b: a > b,
    "==": lambda a, b: a == b,
}
OP_TEXT = {"<=": "≤", "<": "<", ">=": "≥", ">": ">", "==": "=", "~=": "≈"}
PASS, MISS = "✓", "✗"
NO_CHECK = "–"
README_START, README_END = "<!-- bench-table:start -->", "<!-- bench-table:end -->"


@dataclass(frozen=True)
class Check:
    """One machine-checkable part of a row's target: ``metric op value`` or ``metric op ratio × of.metric + plus``."""

    metric: str
    op: Literal["<=", "<", ">=", ">", "==", "~="] = "<="
    value: float | None = None  # an absolute bound, in the metric's unit
    ratio: float | None = None  # bound = ratio × the reference's number (+ plus); default 1 when `of`/`of_metric` given
    of: str = ""  # the reference row (default: this row)
    of_metric: str = ""  # the reference's number (default: `metric`)
    plus: float = 0.0  # added to the ratio bound (an allowed growth, in the metric's unit)
    tol: float = 0.0  # op "~=": the relative difference allowed between measured and bound
    open: str = ""  # a known miss: says why (what is missing). --check reports it apart, does not fail on it

    def __post_init__(self) -> None:
        relative = self.ratio is not None or bool(self.of) or bool(self.of_metric)
        if (self.value is None) == (not relative):
            raise ConfigError(f"check of '{self.metric}': give either value or a reference (ratio / of / of_metric)")
        if relative and not self.of and not self.of_metric:
            raise ConfigError(f"check of '{self.metric}': a ratio needs `of` (a row) or `of_metric` (a number of this row)")
        if self.op not in OP_TEXT:
            raise ConfigError(f"check of '{self.metric}': op must be one of {', '.join(OP_TEXT)}, got {self.op!r}")
        if (self.op == "~=") != (self.tol > 0):
            raise ConfigError(f"check of '{self.metric}': op '~=' needs tol > 0 (a relative tolerance), and tol "
                              f"applies only to '~=' (op {self.op!r}, tol {self.tol!r})")


@dataclass(frozen=True)
class Metric:
    label: str
    unit: str = ""
    fmt: str = ".4g"
    fn: Callable[[dict[str, Any]], Any] | None = None  # derived from the result; None: the result's key of that name


def _ratio(num: str, den: str, scale: float = 1.0) -> Callable[[dict[str, Any]], float | None]:
    def fn(r: dict[str, Any]) -> float | None:
        a, b = r.get(num), r.get(den)
        return None if a is None or not b else scale * a / b
    return fn


def _sim3_scale(r: dict[str, Any]) -> float | None:
    m = re.search(r"s=([0-9.eE+-]+)", str(r.get("align", "")))
    return float(m.group(1)) if m else None


def _mean(key: str) -> Callable[[dict[str, Any]], float | None]:
    """Mean over the grid points where both A and B gave an ATE (as ``batch.ab_result``'s mean_ratio)."""
    def fn(r: dict[str, Any]) -> float | None:
        pairs = [(a, b) for a, b in zip(r.get("ate_a", []), r.get("ate_b", [])) if a is not None and b is not None]
        return statistics.mean(p[0 if key == "a" else 1] for p in pairs) if pairs else None
    return fn


METRICS: dict[str, Metric] = {
    # kind run (vslam.bench.kinds.run.job)
    "ate_rmse": Metric("ATE", "m", ".4f"),
    "ate_rmse_measured": Metric("ATE of the measured frames", "m", ".4f"),
    "ate_pct_path": Metric("ATE", "% of path", ".2f", _ratio("ate_rmse", "path_m", 100.0)),
    "max_map_ate": Metric("ATE of each map", "m", ".4f",
                          lambda r: max(m["ate_rmse"] for m in r["maps"].values()) if r.get("maps") else r.get("ate_rmse")),
    "maps_at_end": Metric("maps at the end", "", "d", lambda r: len(r["maps"]) if r.get("maps") else 1),
    "untracked": Metric("frames not tracked", "", "d",  # of the frames read (posed or not; older rows: posed)
                        lambda r: None if "tracked" not in r else int(r.get("frames_read", r["frames"])) - int(r["tracked"])),
    "posed_fraction": Metric("frames posed", "% of frames read", ".1f",
                             lambda r: 100.0 * r["frames"] / r["frames_read"] if r.get("frames_read") else None),
    "tracked": Metric("frames tracked", "", "d"),
    "lost": Metric("frames lost", "", "d"),
    "new_maps": Metric("new maps", "", "d"),
    "merges": Metric("maps merged", "", "d"),
    "map_switches": Metric("archived maps taken up again", "", "d"),
    "merge_query_ms": Metric("merge query ms/keyframe", "", ".1f"),
    "fps": Metric("frames/s", "", ".1f"),
    "ms_per_frame": Metric("ms/frame", "", ".1f"),
    "rpe_t": Metric("RPE", "m", ".4f"),
    "rpe_r": Metric("RPE", "°", ".3f"),
    "sim3_scale": Metric("Sim3 scale s", "", ".4f", _sim3_scale),
    "stages.mapping_per_kf": Metric("local mapping ms/keyframe", "", ".1f"),
    # kind ab (vslam.bench.batch.ab_result)
    "mean_ratio": Metric("mean ATE B / mean ATE A", "", ".2f"),
    "kf_ms_ratio": Metric("mapping ms/keyframe B / A", "", ".2f"),
    "ate_a_mean": Metric("mean ATE A", "m", ".4f", _mean("a")),
    "ate_b_mean": Metric("mean ATE B", "m", ".4f", _mean("b")),
    # kind sfm (vslam.bench.kinds.sfm): against offline SfM on the same frames
    "sfm_ratio": Metric("ATE / offline SfM ATE", "", ".2f"),
    "sfm_ate": Metric("offline SfM ATE", "m", ".4f"),
    "scale_jump": Metric("largest scale change of a third", "", ".3f"),
    # kind line_ba (vslam.profiling.line_ba_cost)
    "ratio": Metric("CPU per local BA with lines / without", "", ".2f"),
    # kind batch (vslam.bench.batch.batch_row)
    "pool_speedup": Metric("process-pool speed-up", "", ".2f"),
    "ray_speedup": Metric("Ray speed-up", "", ".2f"),
    "pool_identical": Metric("pool metrics = serial (1 = yes)", "", "g", lambda r: _bool(r.get("pool_identical"))),
    "ray_identical": Metric("Ray metrics = serial (1 = yes)", "", "g", lambda r: _bool(r.get("ray_identical"))),
}


def _bool(v: Any) -> float | None:
    return None if v is None else float(bool(v))


class MetricError(ConfigError):
    """A check names a number its row's result does not hold."""


def _walk(node: Any, steps: list[str], metric: str) -> Any:
    """Follow dotted ``steps`` into nested dicts/lists; a key may itself hold dots, or be given by a unique prefix."""
    i = 0
    while i < len(steps):
        if isinstance(node, list):
            try:
                node = node[int(steps[i])]
            except (ValueError, IndexError):
                raise MetricError(f"metric '{metric}': no item '{steps[i]}' in a list of {len(node)}") from None
            i += 1
            continue
        if not isinstance(node, dict):
            raise MetricError(f"metric '{metric}': '{'.'.join(steps[:i])}' is a {type(node).__name__}, not a mapping")
        for j in range(len(steps), i, -1):  # the longest run of steps that is one key ("detector_se_gpu.pt")
            key = ".".join(steps[i:j])
            if key in node:
                node, i = node[key], j
                break
        else:
            hits = [k for k in node if str(k).startswith(steps[i])]
            if len(hits) != 1:
                raise MetricError(f"metric '{metric}': '{steps[i]}' names {len(hits)} of the keys "
                                  f"{', '.join(map(str, node))}")
            node, i = node[hits[0]], i + 1
    return node


def metric_value(result: dict[str, Any], metric: str) -> float | None:
    """The number ``metric`` names in a row's result (None: the result holds it as null / has no such data)."""
    m = METRICS.get(metric)
    if m is not None and m.fn is not None:
        try:
            v = m.fn(result)
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            v = None
    else:
        v = _walk(result, metric.split("."), metric)
    if isinstance(v, bool):
        return float(v)
    if v is None:
        return None
    if not isinstance(v, (int, float)):
        raise MetricError(f"metric '{metric}' is {type(v).__name__} {v!r}, not a number")
    return float(v)


def _label(metric: str) -> tuple[str, str, str]:
    m = METRICS.get(metric)
    return (m.label, m.unit, m.fmt) if m else (metric, "", ".4g")


def fmt_value(metric: str, v: float | None) -> str:
    """``v`` in the metric's format and unit: ``0.0041 m``, ``0.07 % of path``, ``30.0``."""
    if v is None:
        return "–"
    _, unit, fmt = _label(metric)
    text = format(int(v), "d") if fmt == "d" and float(v).is_integer() else format(v, ".4g" if fmt == "d" else fmt)
    return f"{text} {unit}" if unit else text


def check_text(c: Check, row: str = "") -> str:
    """The check as a reader writes it: ``ATE ≤ 1.1x tum-teddy-rgbd``, ``ms/frame ≤ 22``."""
    label, unit, _ = _label(c.metric)
    if c.value is not None:
        rhs = _num(c.value) + (f" {unit}" if unit else "")
    else:
        ref = [c.of] if c.of and c.of != row else []
        if c.of_metric and c.of_metric != c.metric:
            ref.append(_label(c.of_metric)[0])
        ratio = "" if c.ratio in (None, 1.0) else f"{_num(c.ratio)}x "
        rhs = ratio + " ".join(ref) + (f" + {_num(c.plus)}{' ' + unit if unit else ''}" if c.plus else "")
    if c.op == "~=":
        rhs += f" ({tol_text(c).strip()})"
    return f"{label} {OP_TEXT[c.op]} {rhs}"


def tol_text(c: Check) -> str:
    """`` ±10 %`` for a ``~=`` check, "" for the others: what a bound is shown with."""
    return f" ±{_num(100 * c.tol)} %" if c.op == "~=" else ""


def _num(v: float) -> str:
    return format(v, "g")


@dataclass(frozen=True)
class Outcome:
    """One check of one row on the sidecar: measured, bound, status."""

    row: str
    check: Check
    measured: float | None
    bound: float | None
    status: Literal["pass", "miss", "known", "fixed", "unmeasured"]
    why: str = ""  # unmeasured / miss without a number: what was missing

    @property
    def line(self) -> str:
        """``row: metric measured vs target bound (the check as written); open: why``, one line for --check."""
        c = self.check
        got = fmt_value(c.metric, self.measured) if self.measured is not None else (self.why or "no value")
        bound = "–" if self.bound is None else fmt_value(c.metric, self.bound)
        if got == bound and self.measured is not None and self.bound is not None:  # a miss hidden by rounding
            got, bound = format(self.measured, ".6g"), format(self.bound, ".6g")
        text = check_text(c, self.row)
        bound += tol_text(c) if self.bound is not None else ""
        return f"{self.row}: {c.metric} {got} vs target {OP_TEXT[c.op]} {bound} ({text})" + (f"; open: {c.open}" if c.open else "")


def evaluate_check(row: str, c: Check, entries: dict[str, dict[str, Any]]) -> Outcome:
    """Evaluate ``c`` of ``row`` on sidecar ``entries`` (name -> {"result", ...}).

    unmeasured: the row or its reference row is not in the sidecar, or a job was skipped. A row whose job failed
    misses every check, and so does a metric its result does not hold (a typo, or a row that stopped recording
    it: the outcome says which)."""
    def result_of(name: str) -> dict[str, Any] | None:
        e = entries.get(name)
        return None if e is None else e.get("result") or {}

    r = result_of(row)
    if r is None or "skipped" in r:
        return Outcome(row, c, None, None, "unmeasured", "not in BENCHMARKS.json" if r is None else str(r["skipped"]))
    ref_row = c.of or row
    ref = result_of(ref_row) if c.value is None else None
    if c.value is None and (ref is None or "skipped" in ref):
        why = f"{ref_row} not in BENCHMARKS.json" if ref is None else f"{ref_row} not measured ({ref['skipped']})"
        return Outcome(row, c, None, None, "unmeasured", why)
    if "error" in r:
        return Outcome(row, c, None, None, "known" if c.open else "miss", f"failed: {r['error']}")
    bound: float | None
    try:
        measured = metric_value(r, c.metric)
        if c.value is not None:
            bound = float(c.value)
        elif "error" in ref:  # type: ignore[operator]
            return Outcome(row, c, measured, None, "known" if c.open else "miss", f"{ref_row} failed")
        else:
            base = metric_value(ref, c.of_metric or c.metric)  # type: ignore[arg-type]
            bound = None if base is None else (1.0 if c.ratio is None else c.ratio) * base + c.plus
    except MetricError as e:  # a typo in the suite, or a row that no longer records the number: a miss, named
        return Outcome(row, c, None, None, "miss", str(e))
    if measured is None or bound is None or not math.isfinite(measured):
        ok = False
    elif c.op == "~=":
        ok = abs(measured - bound) <= c.tol * abs(bound)
    else:
        ok = OPS[c.op](measured, bound)
    status = ("fixed" if ok else "known") if c.open else ("pass" if ok else "miss")
    return Outcome(row, c, measured, bound, status, "" if measured is not None else "no value")


def evaluate_row(row: Any, entries: dict[str, dict[str, Any]]) -> list[Outcome]:
    """Every check of a BenchRow (anything with ``name`` and ``check``)."""
    return [evaluate_check(row.name, c, entries) for c in row.check]


def verdict(outcomes: list[Outcome], why: bool = False) -> str:
    """A row's mark: ✓ every check met, ✗ one missed, ✗ (open) when every miss is a known one (``why``: with the
    reasons, ✗ (open: speed target not met yet on 2 CPU cores)), – no check or not measured."""
    if not outcomes or all(o.status == "unmeasured" for o in outcomes):
        return NO_CHECK
    if any(o.status == "miss" for o in outcomes):
        return MISS
    known = [o.check.open for o in outcomes if o.status == "known"]
    if known:
        return f"{MISS} (open: {'; '.join(dict.fromkeys(known))})" if why else f"{MISS} (open)"
    return PASS


def target_text(row: Any) -> str:
    """The target a reader sees: the row's own text, else its checks written out."""
    return row.target or "; ".join(check_text(c, row.name) for c in row.check)


def measured_on(entry: dict[str, Any] | None) -> str:
    """``2026-12-05 02:06 UTC, 1a2b3c4`` (commit "–" for rows measured before commits were recorded)."""
    if not entry:
        return "–"
    return f"{entry.get('measured', '–')}, {entry.get('commit') or '–'}"


def git_commit(root: Path) -> str | None:
    """Short hash of HEAD at ``root``, ``-dirty`` when the tree has uncommitted changes; None outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True,
                               timeout=30, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{head}-dirty" if dirty else head or None


def check_report(rows: list[Any], entries: dict[str, dict[str, Any]]) -> tuple[list[str], int]:
    """``vslam bench --check``: (lines to print, exit code). 1 when a check without ``open`` misses.

    Sections: misses (the failure), known misses (open), open checks that now pass (drop their ``open``),
    checks not measured; then a count."""
    outcomes = [o for row in rows for o in evaluate_row(row, entries)]
    by = {s: [o for o in outcomes if o.status == s] for s in ("pass", "miss", "known", "fixed", "unmeasured")}
    lines = []
    if by["miss"]:
        lines += ["Targets missed:", *(f"  {o.line}" for o in by["miss"])]
    if by["known"]:
        lines += ["Known misses (open):", *(f"  {o.line}" for o in by["known"])]
    if by["fixed"]:
        lines += ["Open checks that now pass (remove their `open`):", *(f"  {o.line}" for o in by["fixed"])]
    if by["unmeasured"]:
        lines += ["Not measured:", *(f"  {o.row}: {o.check.metric} ({o.why})" for o in by["unmeasured"])]
    n_rows = len({o.row for o in outcomes})
    lines.append(f"{len(outcomes)} checks on {n_rows} rows: {len(by['pass']) + len(by['fixed'])} pass, "
                 f"{len(by['miss'])} missed, {len(by['known'])} known misses, {len(by['unmeasured'])} not measured")
    # a row the suite checks but the sidecar lacks (never measured, renamed, a lost sidecar) fails like a miss:
    # only a row whose job was skipped (e.g. no GPU) may stay unmeasured
    absent = [o for o in by["unmeasured"] if o.why.endswith("not in BENCHMARKS.json")]
    if absent:
        lines.append(f"{len({o.row for o in absent})} checked rows have no measurement in BENCHMARKS.json "
                     "(run `vslam bench --only ROW`)")
    return lines, 1 if by["miss"] or absent else 0


def _headline_value(row: Any, result: dict[str, Any], outcomes: list[Outcome]) -> str:
    """The row's number for the README: ATE (and ms/frame) of a run, else what its checks measured."""
    if "error" in result:
        return "failed"
    if result.get("ate_rmse") is not None and "ms_per_frame" in result:
        measured = result.get("ate_rmse_measured")
        part = "" if measured is None else f" (measured frames {measured:.4f} m)"
        return f"ATE {result['ate_rmse']:.4f} m{part}, {result['ms_per_frame']:.0f} ms/frame"
    parts = dict.fromkeys(f"{_label(o.check.metric)[0]} {fmt_value(o.check.metric, o.measured)}"
                          for o in outcomes if o.measured is not None)
    return ", ".join(parts) or "–"


def readme_table(rows: list[Any], entries: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown table of the suite's headline rows (``headline:`` their short description), verdicts computed."""
    lines = ["| row | what it measures | ATE / metric | target | ✓/✗ | measured (date, commit) |",
             "|---|---|---|---|---|---|"]
    for row in rows:
        if not row.headline:
            continue
        e = entries.get(row.name)
        outs = evaluate_row(row, entries)
        value = "not measured" if e is None else _headline_value(row, e.get("result") or {}, outs)
        lines.append(f"| {row.name} | {row.headline} | {value} | {_cell(target_text(row))} | {verdict(outs, why=True)} "
                     f"| {measured_on(e)} |")
    return lines


def _cell(text: str) -> str:
    return text.replace("|", "/").replace("\n", " ")


def replace_between_markers(path: Path, body: list[str]) -> bool:
    """Put ``body`` between README_START and README_END in ``path`` (the markers stay); False and a warning
    when the file or a marker is missing, and the file is left as it is."""
    if not path.is_file():
        log.warning("%s: no such file; the results table is not written", path)
        return False
    text = path.read_text()
    start, end = text.find(README_START), text.find(README_END)
    if start < 0 or end < start:
        log.warning("%s: markers %s ... %s not found; the results table is not written", path, README_START, README_END)
        return False
    new = text[: start + len(README_START)] + "\n" + "\n".join(body) + "\n" + text[end:]
    if new != text:
        path.write_text(new)
    return True
