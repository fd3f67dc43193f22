"""Batch evaluation (issue 10): a local process pool and a local Ray instance give exactly the serial run's
metrics on two tiny synthetic sequences; grids and sweeps expand as written."""

from __future__ import annotations

import pytest

from vslam.bench.batch import Job, grid_overrides, parse_sweep, run_jobs, same_metrics
from vslam.config import deep_merge
from vslam.errors import ConfigError

TINY = {"dataset": {"kind": "synthetic", "sensor": "rgbd",
                    "synthetic": {"n_frames": 15, "width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "n_movers": 0}},
        "output": {"report": False}}


def _jobs(root, tag):
    return [Job("run", None, deep_merge(TINY, {"dataset": {"synthetic": {"scene": scene, "seed": seed}}}),
                str(root / f"{tag}-{scene}-{seed}")) for scene, seed in (("room", 0), ("street", 1))]


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    return root, run_jobs(_jobs(root, "serial"))


def test_serial_jobs_measure_two_sequences(serial):
    _, res = serial
    assert all("error" not in r for r in res), res
    assert all(r["frames"] == 15 and r["tracked"] == 15 and r["ate_rmse"] < 0.05 for r in res)
    assert abs(res[0]["path_m"] - res[1]["path_m"]) > 0.1  # two different sequences


def test_process_pool_gives_the_serial_metrics(serial):
    root, ref = serial
    assert same_metrics(ref, run_jobs(_jobs(root, "pool"), workers=2))


def test_ray_gives_the_serial_metrics(serial):
    pytest.importorskip("ray")
    root, ref = serial
    res = run_jobs(_jobs(root, "ray"), workers=2, ray="")
    assert all("error" not in r for r in res), res
    assert same_metrics(ref, res)


def test_grids_and_sweeps_expand():
    assert grid_overrides({"a.b": [1, 2], "c": ["x"]}) == [{"a": {"b": 1}, "c": "x"}, {"a": {"b": 2}, "c": "x"}]
    assert parse_sweep(["slam.x=0,0.5", "k=true"]) == {"slam.x": [0, 0.5], "k": [True]}
    with pytest.raises(ConfigError, match="KEY=V1"):
        parse_sweep(["nokey"])
    with pytest.raises(ConfigError, match="non-empty list"):
        grid_overrides({"a": 3})
    assert not same_metrics([{"ate_rmse": 1.0}], [{"ate_rmse": 1.0 + 1e-12}])
    assert not same_metrics([{"ate_rmse": 1.0}], [])
