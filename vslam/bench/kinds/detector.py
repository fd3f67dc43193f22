"""Kinds ``detector`` (the attention ablation) and ``eval_detector`` (a detector on real validation photos)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from vslam.bench.suite import BenchRow
from vslam.bench.tables import report_tables
from vslam.childproc import peak_rss_mb
from vslam.errors import ConfigError


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Dynamic-object filtering: the attention ablation (``set``: weights=[files], all trained with one recipe;
    ``eval.ablation``)."""
    from vslam.eval.ablation import evaluate_detectors

    t0 = time.perf_counter()
    weights = [str(w) for w in overrides.get("weights", ())]
    if not weights:
        raise ConfigError("bench kind detector needs set: weights=[file, ...]")
    res = evaluate_detectors(weights, threads=int(overrides.get("threads", 2)))
    return {**res, "seconds": time.perf_counter() - t0, "peak_rss_mb": peak_rss_mb()}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Dynamic-object filtering: detectors on the held-out sets (the attention ablation: one recipe, one seed)."""
    from vslam.eval.ablation import format_table

    return report_tables(rows, "## Dynamic-object detector (`{name}`)", format_table)


def job_eval(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Detector data: ``vslam eval-detector`` over several labelled folders. ``set``: data=[folder:split, ...] (under
    $VSLAM_DATA), model (checkpoint; "" = the shipped one) or teacher=true (FastestDet), img_size, threads ->
    {"sets": {"<folder's first part>-<split>": the evaluator's report}}."""
    from vslam.eval.detector import build_detector, evaluate, predict
    from vslam.paths import data_root
    from vslam.train.photos import load_records

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


def eval_table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Detector data: a detector on the real validation splits (``vslam eval-detector``), one table per folder."""
    from vslam.eval.detector import format_report

    def tables(r: dict[str, Any]) -> list[str]:
        out = [f"{r['model']}, recall / precision / mask IoU at score {r['threshold']:g}"]
        for name, rep in r["sets"].items():
            out += ["", f"{name} ({rep['images']} images):", "", *format_report(rep, name)]
        return out

    return report_tables(rows, "## Detector on real photos (`{name}`)", tables)
