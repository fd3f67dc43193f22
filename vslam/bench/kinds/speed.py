"""Kinds ``speed`` (the learned front end's networks per device) and ``line_ba`` (back-end cost of lines)."""

from __future__ import annotations

from typing import Any


from vslam.bench.suite import BenchRow
from vslam.bench.tables import fmt, md_failed_row, md_section


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Speed: the learned front end's networks, ms per frame on one device (``profiling.network_speed``;
    ``set``: device, frames, repeats, threads). device=cuda on a machine without a GPU is skipped, not failed:
    the row keeps what a GPU machine measured."""
    import torch

    from vslam.profiling import network_speed

    device = str(overrides.get("device", "auto"))
    if device == "cuda" and not torch.cuda.is_available():
        return {"skipped": "no CUDA device here"}
    return network_speed(device, frames=int(overrides.get("frames", 20)), repeats=int(overrides.get("repeats", 3)),
                         threads=int(overrides.get("threads", 2)))


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Speed: the learned front end's networks per device, one table for all such rows."""
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


def job_line_ba(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.profiling import line_ba_cost

    return line_ba_cost(config, overrides, out_dir)


def line_ba_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Line features: back-end CPU of lines, each local BA solved without and with its lines
    (``profiling.line_ba_cost``)."""
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
                     f"{fmt(r.get('ate_rmse'), '.4f')} | {row.target} |")
    return lines
