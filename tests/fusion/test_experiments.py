"""Experiments: quick runs write plots, report and JSON metrics; the CLI registers."""

from __future__ import annotations

import argparse
import json

import pytest

from vslam.cli.fusion import add_cli
from vslam.fusion.experiments import EXPERIMENTS


@pytest.mark.parametrize("name", sorted(set(EXPERIMENTS) - {"validity_vslam"}))  # runs vslam: test_exp_vslam.py
def test_quick_experiment_writes_report(name, tmp_path):
    m = EXPERIMENTS[name](tmp_path, seed=0, quick=True)
    assert "seed_claim" in m and "ours" in m
    assert (tmp_path / "report.md").read_text().startswith("# ")
    assert json.loads((tmp_path / "metrics.json").read_text()) == m
    assert list(tmp_path.glob("*.png"))
    if name == "ins_gnss":
        assert m["ours"]["arsckf_vs_ckf_pos_pct"] > 20.0
    if name == "validity":
        blk = m["ours"]["rms_gnss_blocked"]
        assert blk["r_opt"] < 0.7 * blk["GNSS+INS"]  # switching to the visual estimate pays off
    if name == "multi_vehicle":
        ex = m["ours"]["exact_mutual"]
        assert ex["vector_pos"] == pytest.approx(ex["two_stage_pos"], rel=1e-3)


def test_cli_registers_fusion():
    p = argparse.ArgumentParser()
    add_cli(p.add_subparsers(dest="cmd"))
    a = p.parse_args(["fusion", "validity", "--quick", "--seed", "3", "--out", "x"])
    assert a.experiment == "validity" and a.quick and a.seed == 3 and callable(a.fn)
