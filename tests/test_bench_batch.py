"""`vslam bench` parallel paths (issue 10): a "batch" row (serial vs pool vs Ray on a grid), ``--jobs`` and
``--sweep``."""

from __future__ import annotations

import json

from vslam.bench import run_bench

TINY = ("dataset:\n  kind: synthetic\n  synthetic: {n_frames: 10, width: 320, height: 240, fx: 262.5, fy: 262.5, n_movers: 0}\n"
        "output:\n  report: false\n")


def _suite(tmp_path, rows: str):
    (tmp_path / "configs").mkdir(exist_ok=True)
    (tmp_path / "configs" / "tiny.yaml").write_text(TINY)
    suite = tmp_path / "configs" / "suite.yaml"
    suite.write_text("title: tiny\nrows:\n" + rows)
    return suite


def test_batch_row_compares_serial_pool_and_ray(tmp_path):
    suite = _suite(tmp_path, "  - name: tiny-batch\n    kind: batch\n    config: configs/tiny.yaml\n    workers: 2\n"
                             "    grid: {dataset.synthetic.seed: [0, 1]}\n    target: same metrics\n")
    text = run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs").read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("| tiny-batch"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[1] == "2" and cells[2] == "2"  # jobs, workers
    r = json.loads((tmp_path / "B.json").read_text())["rows"]["tiny-batch"]["result"]
    assert r["errors"] == 0 and r["pool_identical"] is True
    assert r.get("ray_identical", True) is True  # absent only when ray is not installed (then said in the row)
    assert cells[6].startswith("yes /")


def test_jobs_and_sweep(tmp_path):
    suite = _suite(tmp_path, "  - {name: a, config: configs/tiny.yaml}\n  - {name: b, config: configs/tiny.yaml, "
                             "set: [dataset.synthetic.seed=1]}\n")
    serial = json.loads(run_bench(suite, tmp_path / "S.md", jobs_dir=tmp_path / "r1").with_suffix(".json").read_text())
    par = json.loads(run_bench(suite, tmp_path / "P.md", jobs_dir=tmp_path / "r2", workers=2).with_suffix(".json").read_text())
    for name in ("a", "b"):
        assert serial["rows"][name]["result"]["ate_rmse"] == par["rows"][name]["result"]["ate_rmse"]
    assert "2 jobs at a time" in (tmp_path / "P.md").read_text()
    out = run_bench(suite, tmp_path / "W.md", only=["a"], jobs_dir=tmp_path / "r3",
                    sweep={"slam.backend.rgbd_disparity_sigma": [0.0, 0.1]})
    rows = json.loads(out.with_suffix(".json").read_text())["rows"]
    assert set(rows) == {"a[slam.backend.rgbd_disparity_sigma=0.0]", "a[slam.backend.rgbd_disparity_sigma=0.1]"}
    assert rows["a[slam.backend.rgbd_disparity_sigma=0.1]"]["result"]["ate_rmse"] == serial["rows"]["a"]["result"]["ate_rmse"]


def test_ab_row_runs_both_sides_on_every_seed(tmp_path):
    """Kind "ab": A and B per grid point, B/A per point and the ratio of the means; A equals a plain run."""
    suite = _suite(tmp_path, "  - name: tiny-ab\n    kind: ab\n    config: configs/tiny.yaml\n"
                             "    treatment: [slam.features.n_features=400]\n"
                             "    grid: {dataset.synthetic.seed: [0, 1]}\n    target: some target\n"
                             "  - {name: plain, config: configs/tiny.yaml, set: [dataset.synthetic.seed=1]}\n")
    text = run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs", workers=2).read_text()
    rows = json.loads((tmp_path / "B.json").read_text())["rows"]
    r = rows["tiny-ab"]["result"]
    assert r["points"] == ["dataset.synthetic.seed=0", "dataset.synthetic.seed=1"] and not r["errors"]
    assert r["ate_a"][1] == rows["plain"]["result"]["ate_rmse"]  # the A side is the row's config as it is
    assert r["ratios"] == [b / a for a, b in zip(r["ate_a"], r["ate_b"])]
    assert abs(r["mean_ratio"] - sum(r["ate_b"]) / sum(r["ate_a"])) < 1e-12
    assert r["ate_a"] != r["ate_b"]  # the treatment reached the B runs
    line = next(ln for ln in text.splitlines() if ln.startswith("| tiny-ab"))
    assert "slam.features.n_features=400" in line and f"**{r['mean_ratio']:.2f}x**" in line and "some target" in line


def test_ab_table_names_the_first_failed_run():
    """A failed run's error reaches the table (one line, no cell break), not only BENCHMARKS.json."""
    from vslam.bench.batch import ab_result, ab_table
    from vslam.bench import BenchRow

    row = BenchRow(name="x-ab", kind="ab", treatment=("k=1",), target="t")
    res = ab_result({"seed": [0, 1]}, [{"ate_rmse": 0.01}, {"ate_rmse": 0.02},
                                       {"error": "ConfigError: a|b.yaml:\n not found"}, {"error": "other"}])
    line = next(ln for ln in ab_table([(row, res)]) if ln.startswith("| x-ab"))
    assert "2 (2 runs failed: ConfigError: a/b.yaml: not found)" in line and "**2.00x**" in line
