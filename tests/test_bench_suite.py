"""Every row of the shipped suite (configs/bench.yaml) that runs the pipeline names a config that loads with its
overrides: a renamed or moved config key fails here, not on the next day's bench run."""

from __future__ import annotations

from pathlib import Path

import pytest

from vslam.bench import load_suite
from vslam.config import deep_merge, load_yaml, parse_overrides
from vslam.pipeline import PipelineConfig

ROOT = Path(__file__).resolve().parents[1]
SUITE = ROOT / "configs" / "bench.yaml"


def _pipeline_rows():
    if not SUITE.is_file():
        return []
    return [r for r in load_suite(SUITE).rows if r.kind in ("run", "ab", "batch", "sfm") and r.config]


@pytest.mark.skipif(not SUITE.is_file(), reason="no configs/bench.yaml (installed package, not a checkout)")
@pytest.mark.parametrize("row", _pipeline_rows(), ids=lambda r: r.name)
def test_row_config_and_overrides_load(row):
    from vslam.resources import resolve_config

    path = resolve_config(ROOT / row.config if (ROOT / row.config).exists() else row.config)
    over = parse_overrides(list(row.set) + list(row.treatment))
    for key, values in (row.grid or {}).items():  # a grid's first value stands for the rest (same key)
        over = deep_merge(over, parse_overrides([f"{key}={values[0] if isinstance(values, list) else values}"]))
    if row.kind == "sfm":  # the reference's own settings (sfm.<key>) are not pipeline keys
        from vslam.bench.kinds.sfm import SfmOptions
        from vslam.config import from_dict

        from_dict(SfmOptions, over.pop("sfm", None) or {}, row.name)
    PipelineConfig.load(path, over)
    assert isinstance(load_yaml(path), dict)
