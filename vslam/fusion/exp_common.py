"""Shared output helpers of the fusion experiments: Agg figures, metrics.json, report.md."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any


def pyplot():
    """matplotlib.pyplot with the non-interactive Agg backend (set here, not at import time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def clean(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars/arrays -> Python, NaN/inf -> None, dict keys -> str."""
    if isinstance(obj, dict):
        return {str(k): clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    if hasattr(obj, "tolist"):
        return clean(obj.tolist())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def md_table(header: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def write_outputs(out_dir: Path, title: str, metrics: dict[str, Any], sections: list[str],
                  figures: list[str], config: dict[str, Any]) -> dict[str, Any]:
    """Write metrics.json + report.md (sections, figure links, resolved config); return clean metrics."""
    out_dir.mkdir(parents=True, exist_ok=True)
    m = clean(metrics)
    (out_dir / "metrics.json").write_text(json.dumps(m, indent=2))
    body = [f"# {title}", "", f"Seed claim: {m.get('seed_claim', '')}", ""] + sections
    body += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    body += ["", "## Resolved config", "", "```json", json.dumps(clean(config), indent=2), "```", ""]
    (out_dir / "report.md").write_text("\n".join(body))
    return m
