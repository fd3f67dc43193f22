"""Markdown pieces every kind's table uses."""

from __future__ import annotations

from typing import Any


from vslam.bench.suite import BenchRow


def fmt(v: Any, spec: str) -> str:
    return "–" if v is None else format(v, spec)

def md_section(title: str, intro: str, columns: list[str]) -> list[str]:
    """Lines opening a BENCHMARKS.md section: ``## title``, an intro paragraph, a table head of ``columns``."""
    return ["", f"## {title}", "", intro, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]

def md_failed_row(row: BenchRow, error: str, n_columns: int) -> str:
    """A table line for a row whose job failed: name, the error, empty cells, the target in the last column."""
    return f"| {row.name} | **failed**: {error} |" + " |" * (n_columns - 3) + f" {row.target} |"

def report_tables(rows: list[tuple[BenchRow, dict[str, Any]]], heading: str, format_table: Any) -> list[str]:
    """One section per row: ``heading`` (with the row's name), the row's own table, its target."""
    lines = []
    for row, r in rows:
        lines += ["", heading.format(name=row.name), ""]
        if "error" in r:
            lines.append(f"**failed**: {r['error']}")
            continue
        lines += [*format_table(r), "", f"Target: {row.target}"]
    return lines
