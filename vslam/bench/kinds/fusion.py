"""Kind ``fusion``: the navigation-fusion experiments of the seed papers (``vslam.fusion.experiments``)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any


from vslam.bench.suite import BenchRow
from vslam.childproc import peak_rss_mb
from vslam.errors import ConfigError


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.fusion.experiments import EXPERIMENTS

    experiment = str(config)
    if experiment not in EXPERIMENTS:
        raise ConfigError(f"unknown fusion experiment {experiment!r}; known: {', '.join(sorted(EXPERIMENTS))}")
    t0 = time.perf_counter()
    m = EXPERIMENTS[experiment](Path(out_dir), seed=int(overrides.get("seed", 0)), quick=bool(overrides.get("quick", False)))
    return {"headline": m.get("headline", ""), "seed_claim": m.get("seed_claim", ""), "seconds": time.perf_counter() - t0,
            "report": str(Path(out_dir) / "report.md"), "peak_rss_mb": peak_rss_mb()}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """The navigation-fusion experiments, one line each."""
    lines: list[str] = []
    if rows:
        lines += ["", "## Navigation fusion experiments (seeds 000, 002, 003 ch. 2, 004)", "",
                  "| experiment | ours | seed claim | s | report |", "|---|---|---|---|---|"]
        for row, r in rows:
            if "error" in r:
                lines.append(f"| {row.name} | **failed**: {r['error']} | | | |")
            else:
                lines.append(f"| {row.name} | {r['headline']} | {r['seed_claim']} | {r['seconds']:.0f} | `{r['report']}` |")
    return lines
