"""Kind ``place``: recall of the place descriptors and the keyframe database's cost."""

from __future__ import annotations

import time
from typing import Any

from vslam.bench.suite import BenchRow
from vslam.bench.tables import md_failed_row, md_section
from vslam.childproc import peak_rss_mb


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    """Place recognition: recall@1/5/10 of the place descriptors (``set``: descriptors=[bow, vladnet], weights=<file>,
    seed=<held-out synthetic route>, tum=<folder under $VSLAM_DATA>) and the keyframe database's cost at 10k."""
    from vslam.eval.place import bow_describer, database_costs, evaluate_held_out, held_out_sets, vladnet_describer
    from vslam.loop.descriptor import default_vladnet_path
    from vslam.paths import data_root

    t0 = time.perf_counter()
    names = [str(n) for n in overrides.get("descriptors", ("bow", "vladnet"))]
    make = {"bow": bow_describer, "vladnet": lambda: vladnet_describer(str(overrides.get("weights") or default_vladnet_path()))}
    desc = {n: make[n]() for n in names}
    held = held_out_sets(int(overrides.get("seed", 0)), int(overrides.get("frames", 600)), stride=int(overrides.get("stride", 3)),
                         tum=data_root() / str(overrides.get("tum", "tum/rgbd_dataset_freiburg3_teddy")),
                         tum_split=int(overrides.get("tum_split", 100)))
    sets = {held[k].label: r for k, r in evaluate_held_out(desc, held).items()}
    dims = {n: next(iter(sets.values()))[n]["dim"] for n in names}
    return {"sets": sets, "costs": {n: database_costs(d) for n, d in dims.items()}, "seconds": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb()}


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """Place recognition, retrieval: recall@k per evaluation set and descriptor, then the database cost at 10k
    keyframes."""
    if not rows:
        return []
    lines = md_section("Place recognition",
                       "A query counts when the database holds a frame of the same place; recalled at k when one of its k "
                       "most similar database frames is one. BoW: tf-idf of 512 ORB words on the tracker's keypoints (full "
                       "image); VLADNet: vslam/models/vladnet_v1.pt on the image (its model card says what it was trained on: not "
                       "these sets).",
                       ["row", "set", "descriptor", "queries", "R@1", "R@5", "R@10", "ms / image", "target"])
    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 9))
            continue
        for set_name, res in r["sets"].items():
            for d, m in res.items():
                lines.append(f"| {row.name} | {set_name} | {d} | {m['queries']} | {m['r@1']:.2f} | {m['r@5']:.2f} "
                             f"| {m['r@10']:.2f} | {m['ms_per_image']:.1f} | {row.target} |")
    lines += ["", "| row | descriptor | bytes per keyframe | query over 10k keyframes ms |", "|---|---|---|---|"]
    for row, r in rows:
        for d, c in r.get("costs", {}).items():
            lines.append(f"| {row.name} | {d} | {c['bytes_per_keyframe']} | {c['query_ms']:.2f} |")
    return lines
