"""The bench kind detector_speed (vslam.bench.kinds.detector_speed): its table and its one-line errors."""

from __future__ import annotations

import pytest

from vslam.bench.kinds import job_function, table_function
from vslam.bench.suite import BenchRow
from vslam.errors import ConfigError


def test_table_gives_each_model_and_the_ratio():
    r = {"frames": 30, "threads": 2, "shape": [480, 640],
         "models": {"boxes": {"ms_median": 20.0, "ms_min": 18.0, "detections": 3.0, "masks": False},
                    "masks": {"ms_median": 25.0, "ms_min": 22.0, "detections": 3.0, "masks": True}}}
    lines = table_function("detector_speed")([(BenchRow("speed-row", kind="detector_speed", target="fast"), r)])
    assert "## Detector speed (`speed-row`)" in lines
    assert "| boxes | 20.0 | 18.0 | 3.0 | no | 1.00 |" in lines and "| masks | 25.0 | 22.0 | 3.0 | yes | 1.25 |" in lines
    assert lines[-1] == "Target: fast"


def test_models_must_be_named_and_distinct(tmp_path):
    job = job_function("detector_speed")
    with pytest.raises(ConfigError, match="models="):
        job(None, {}, str(tmp_path))
    with pytest.raises(ConfigError, match="distinct names"):
        job(None, {"models": ["a/x.pt", "b/x.pt"]}, str(tmp_path))
