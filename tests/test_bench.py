"""`vslam bench` writes BENCHMARKS.md rows from real runs in fresh processes."""

from __future__ import annotations

import pytest

from vslam.bench import load_suite, run_bench
from vslam.errors import ConfigError


def test_bench_writes_rows_with_machine_and_determinism(tmp_path):
    suite = tmp_path / "configs" / "suite.yaml"
    suite.parent.mkdir()
    (tmp_path / "configs" / "tiny.yaml").write_text(
        "dataset:\n  kind: synthetic\n  synthetic: {n_frames: 12, width: 320, height: 240, fx: 262.5, fy: 262.5}\n"
        "output:\n  report: false\n"
    )
    suite.write_text(
        "title: tiny\nrows:\n"
        "  - {name: tiny-rgbd, config: configs/tiny.yaml, target: 'none'}\n"
        "  - {name: tiny-render, kind: synthetic_render, config: configs/tiny.yaml}\n"
        "  - {name: tiny-fusion, kind: fusion, experiment: identification, set: [quick=true]}\n"
    )
    out = run_bench(suite, tmp_path / "BENCH.md", repeat=2, jobs_dir=tmp_path / "runs")
    text = out.read_text()
    assert "Machine:" in text and "logical cores" in text
    rows = {ln.split("|")[1].strip(): ln for ln in text.splitlines() if ln.startswith("| tiny")}
    assert {"tiny-rgbd", "tiny-render"} <= set(rows)
    cells = [c.strip() for c in rows["tiny-rgbd"].split("|")]
    assert cells[2] == "12 (12)"  # frames (tracked)
    assert float(cells[3]) > 0.05  # the path length of the synthetic camera, metres
    assert float(cells[4].split()[0]) < 0.05  # ATE of a 12-frame synthetic run
    assert cells[11] == "yes"  # two runs, identical ATE
    assert (tmp_path / "runs" / "tiny-rgbd-1" / "trajectory.tum.txt").is_file()
    fusion = next(ln for ln in text.splitlines() if ln.startswith("| tiny-fusion"))
    assert "max posterior at 0.9 s: N=3" in fusion and "seed 002" in fusion
    assert (tmp_path / "runs" / "tiny-fusion" / "report.md").is_file()


def test_bad_suite(tmp_path):
    s = tmp_path / "s.yaml"
    s.write_text("rows:\n  - {name: x, kind: nope}\n")
    with pytest.raises(ConfigError, match="rows\\[0\\].kind"):
        load_suite(s)
    s.write_text("rows: []\n")
    with pytest.raises(ConfigError, match="no rows"):
        load_suite(s)
