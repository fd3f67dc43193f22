"""``vslam run --profile``: where each frame's time goes, stage by stage, and the peak memory (issue 10).

Read back from the run's ``stats.csv``, so a profile costs the run nothing extra and any finished run can be
profiled again (``python -m vslam.profiling runs/x/stats.csv``). Per stage: the mean ms per frame (a stage that
runs on keyframes only, such as local BA, counts 0 on the other frames, so the means add up to the frame
time), the median over the frames it ran on, how many frames that was, and its share of the mean total.
"decode" is the time tracking waited for the next frame (frames are read on a background thread). With
``slam.frontend_thread`` (the default) that thread also computes the image-only stages (features, lines, the
dynamic-object detector and, without dynamic filtering, depth) ahead of tracking: their rows are then their cost
there, on the second core, and not part of "total" (the tracking call); "decode" includes any wait for them.
"""

from __future__ import annotations

import csv
import json
import resource
import statistics
import sys
from pathlib import Path
from typing import Any

#: pipeline order; sub-stages of mapping are indented in the table
ORDER = ("decode", "features", "detector", "dynamic", "lines", "depth", "pose", "mapping", "map_create",
         "map_fuse_cull", "map_ba", "map_wait", "map_loop", "total")


def profile(stats_csv: str | Path) -> dict[str, Any]:
    """-> {"frames": N, "stages": {stage: {"mean_ms", "median_ms", "frames", "share"}}, "peak_rss_mb": this process}."""
    with open(stats_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    cols = [c[3:] for c in (rows[0] if rows else {}) if c.startswith("ms_")]
    stages: dict[str, dict[str, float]] = {}
    for col in sorted(cols, key=lambda c: ORDER.index(c) if c in ORDER else len(ORDER)):
        ran = [float(r["ms_" + col]) for r in rows if r.get("ms_" + col, "") not in ("", None)]
        if not ran:
            continue
        stages[col] = {"mean_ms": sum(ran) / len(rows), "median_ms": statistics.median(ran), "frames": len(ran)}
    total = stages.get("total", {}).get("mean_ms", 0.0)
    for st in stages.values():
        st["share"] = st["mean_ms"] / total if total > 0 else float("nan")
    # the frame rate counts the waits for frames too: with the front-end thread, the time tracking waited for
    # features ("decode") is outside "total" but not outside the run
    wall = total + stages.get("decode", {}).get("mean_ms", 0.0)
    return {"frames": len(rows), "stages": stages, "wall_ms_per_frame": wall,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def format_profile(p: dict[str, Any]) -> str:
    """A fixed-width table of ``profile``'s result."""
    lines = [f"{'stage':<16}{'mean ms/frame':>14}{'median ms':>11}{'frames':>8}{'share':>8}"]
    for name, st in p["stages"].items():
        label = ("  " + name[4:]) if name.startswith("map_") else name
        lines.append(f"{label:<16}{st['mean_ms']:>14.1f}{st['median_ms']:>11.1f}{st['frames']:>8d}{100 * st['share']:>7.0f}%")
    wall = p.get("wall_ms_per_frame")
    fps = f", {1e3 / wall:.1f} frames/s (tracking + waiting for frames)" if wall else ""
    lines.append(f"{p['frames']} frames{fps}, peak RSS {p['peak_rss_mb']:.0f} MB")
    return "\n".join(lines)


def write_profile(stats_csv: str | Path, out: str | Path) -> dict[str, Any]:
    p = profile(stats_csv)
    Path(out).write_text(json.dumps(p, indent=1) + "\n")
    return p


if __name__ == "__main__":  # profile a finished run: python -m vslam.profiling runs/x/stats.csv
    print(format_profile(profile(sys.argv[1])))
