"""`vslam bench` writes BENCHMARKS.md rows from real runs in fresh processes."""

from __future__ import annotations

import pytest

import json
from pathlib import Path

from vslam.bench import load_sidecar, load_suite, run_bench, stage_times
from vslam.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


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
    main, stages = text.split("## Time per stage")
    rows = {ln.split("|")[1].strip(): ln for ln in main.splitlines() if ln.startswith("| tiny")}
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
    # per-stage table (issue 3): one row per SLAM run, features/pose/mapping and the BA sub-stage
    stage_head = next(ln for ln in stages.splitlines() if ln.startswith("| row | features"))
    heads = [c.strip() for c in stage_head.split("|")[1:-1]]
    assert {"features", "depth", "pose", "mapping", "map: ba", "keyframes", "total"} <= set(heads)
    stage = next(ln for ln in stages.splitlines() if ln.startswith("| tiny-rgbd"))
    vals = dict(zip(heads, [c.strip() for c in stage.split("|")[1:-1]]))
    assert float(vals["features"]) > 0 and float(vals["total"]) > 0  # no order: features run on the front-end thread
    assert float(vals["map: ba"]) > 0 and int(vals["keyframes"]) >= 1
    assert not any(ln.startswith("| tiny-render") for ln in stages.splitlines())

    # --only re-measures one row and keeps the others from the sidecar, word for word
    side = json.loads((tmp_path / "BENCH.json").read_text())
    assert set(side["rows"]) == {"tiny-rgbd", "tiny-render", "tiny-fusion"}
    side["rows"]["tiny-rgbd"]["measured"] = "2000-01-01 00:00 UTC"  # an earlier session
    (tmp_path / "BENCH.json").write_text(json.dumps(side))
    run_bench(suite, tmp_path / "BENCH.md", repeat=1, only=["tiny-render"], jobs_dir=tmp_path / "runs2")
    text2 = out.read_text()
    rows2 = {ln.split("|")[1].strip(): ln for ln in text2.split("## Time per stage")[0].splitlines() if ln.startswith("| tiny")}
    assert rows2["tiny-rgbd"] == rows["tiny-rgbd"] and fusion in text2.splitlines()
    assert "- 2000-01-01 00:00 UTC, 2 run(s) per row: tiny-rgbd" in text2
    assert "1 run(s) per row: tiny-render" in text2
    assert not (tmp_path / "runs2" / "tiny-rgbd-0").exists()
    with pytest.raises(ConfigError, match="no row named nope"):
        run_bench(suite, tmp_path / "BENCH.md", only=["nope"], jobs_dir=tmp_path / "runs3")


def test_bad_suite(tmp_path):
    s = tmp_path / "s.yaml"
    s.write_text("rows:\n  - {name: x, kind: nope}\n")
    with pytest.raises(ConfigError, match="rows\\[0\\].kind"):
        load_suite(s)
    s.write_text("rows: []\n")
    with pytest.raises(ConfigError, match="no rows"):
        load_suite(s)


def test_stage_times_from_stats_csv(tmp_path):
    p = tmp_path / "stats.csv"
    p.write_text(
        "index,tracked,ms_features,ms_depth,ms_pose,ms_mapping,ms_map_create,ms_map_ba,ms_map_loop,ms_total\n"
        "0,1,10,1,5,40,10,30,,56\n"
        "1,1,12,1,7,0.5,,,,20.5\n"
        "2,1,14,1,9,0.5,,,,24.5\n"
        "3,1,16,1,11,80,20,60,,108\n"
    )
    st = stage_times(p)
    assert st["keyframes"] == 2
    s = st["stages"]
    assert s["features"] == 13 and s["pose"] == 8 and s["total"] == 40.25  # medians per frame
    assert s["mapping"] == 30.25 and s["map_ba"] == 22.5 and s["map_create"] == 7.5  # means per frame (blank = 0)
    assert s["mapping_per_kf"] == 60  # median over the two keyframes
    assert "map_loop" not in s  # a stage that never ran is not a 0 ms stage
    assert stage_times(tmp_path / "missing.csv") == {}


def test_unreadable_sidecar_is_ignored(tmp_path, caplog):
    p = tmp_path / "B.json"
    p.write_text("{not json")
    assert load_sidecar(p) == {}
    p.write_text('{"version": 99, "rows": {}}')
    assert load_sidecar(p) == {}
    assert "ignoring the earlier rows" in caplog.text


def test_make_dynamic_rows_name_their_sequence(tmp_path):
    from vslam.bench import _composited

    with pytest.raises(ConfigError, match="needs 'data'"):
        _composited({"people": 2}, tmp_path)
    with pytest.raises(ConfigError, match="takes people, seed .seeds: kind ab., coco"):
        _composited({"data": "tum/x", "walkers": 2}, tmp_path)
    done = tmp_path / "_data" / "x-people2-seed1"
    done.mkdir(parents=True)
    (done / "boxes.txt").write_text("# already composited\n")  # written last, once, then reused as it is
    assert _composited({"data": "tum/x", "people": 2, "seed": 1}, tmp_path) == ("tum", done.resolve())


def test_ab_rows_over_composites_run_one_grid_point_per_walker_seed(tmp_path, monkeypatch):
    """make_dynamic seeds: A and B run on each seed's composite (same folder for both), the table names seeds."""
    import vslam.batch
    import vslam.bench

    monkeypatch.setattr(vslam.bench, "_composited", lambda spec, jobs_dir: ("tum", tmp_path / f"walkers-{spec['seed']}"))
    seen = []

    def fake_run_jobs(jobs, workers, ray):
        seen.extend(jobs)
        return [{"ate_rmse": 0.001 * (i + 1)} for i in range(len(jobs))]

    monkeypatch.setattr(vslam.batch, "run_jobs", fake_run_jobs)
    suite = tmp_path / "configs" / "suite.yaml"
    suite.parent.mkdir()
    suite.write_text("rows:\n  - name: people-seeds\n    kind: ab\n    config: configs/x.yaml\n"
                     "    set: [slam.dynamic.source=gt_mask]\n    treatment: [slam.dynamic.source=detector]\n"
                     "    make_dynamic: {data: tum/teddy, people: 3, seeds: [0, 7]}\n")
    run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs")
    assert [j.overrides["dataset"]["path"] for j in seen] == [str(tmp_path / f"walkers-{s}") for s in (0, 0, 7, 7)]
    assert [j.overrides["slam"]["dynamic"]["source"] for j in seen] == ["gt_mask", "detector"] * 2
    assert {j.overrides["dataset"]["kind"] for j in seen} == {"tum"}
    r = load_sidecar(tmp_path / "B.json")["people-seeds"]["result"]
    assert r["points"] == ["make_dynamic.seed=0", "make_dynamic.seed=7"]
    assert r["ate_a"] == [0.001, 0.003] and r["ate_b"] == [0.002, 0.004]
    assert r["mean_ratio"] == pytest.approx(0.003 / 0.002)
    assert "**1.50x** (0.0020 → 0.0030 m)" in (tmp_path / "B.md").read_text()  # the means the target speaks of
    suite.write_text(suite.read_text().replace("kind: ab", "kind: run"))
    with pytest.raises(ConfigError, match="seeds: \\[..\\] is for kind ab rows"):
        run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs")


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="tests the row of a machine without a GPU")
def test_gpu_speed_row_is_skipped_without_a_gpu_and_keeps_its_measurement(tmp_path):
    """A GPU row run where torch sees no GPU neither fails nor overwrites what a GPU machine measured."""
    suite = tmp_path / "configs" / "suite.yaml"
    suite.parent.mkdir()
    suite.write_text("title: t\nrows:\n  - {name: gpu, kind: speed, set: [device=cuda], target: 'fast'}\n")
    out = run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs")
    assert "- gpu: no CUDA device here" in out.read_text()
    side = json.loads((tmp_path / "B.json").read_text())
    side["rows"]["gpu"] = {"result": {"device": "cuda", "device_name": "NVIDIA H200", "torch": "2.11",
                                      "ms": {"convpoint": 4.6, "detector": 4.7, "lines": 18.8, "vladnet": 1.5,
                                             "front_end": 28.3}, "peak_gpu_mb": 69.0},
                           "measured": "2026-12-04 11:47 UTC", "repeat": 1, "machine": "the GPU machine"}
    (tmp_path / "B.json").write_text(json.dumps(side))
    text = run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs").read_text()
    assert "| gpu | NVIDIA H200 (torch 2.11) | 4.6 | 4.7 | 18.8 | 1.5 | 28.3 | 69 MB |" in text
    assert "on the GPU machine" in text and "Target: fast" in text


def test_line_ba_row_solves_each_window_twice_and_keeps_the_run_with_lines(tmp_path):
    """Kind line_ba (issue 6): every local BA with lines is timed without and with them on the same window; the
    run itself goes on with the lines, so its trajectory is a plain run's with lines on."""
    from vslam.pipeline import Pipeline, PipelineConfig

    (tmp_path / "configs").mkdir()
    sets = "[dataset.synthetic.scene=corridor, dataset.synthetic.n_movers=0, dataset.synthetic.n_frames=45]"
    (tmp_path / "configs" / "suite.yaml").write_text(
        f"title: t\nrows:\n  - {{name: lb, kind: line_ba, config: {ROOT / 'configs/synthetic.yaml'}, set: {sets}, "
        "target: 'cheap'}\n")
    text = run_bench(tmp_path / "configs" / "suite.yaml", tmp_path / "B.md", jobs_dir=tmp_path / "runs").read_text()
    r = json.loads((tmp_path / "B.json").read_text())["rows"]["lb"]["result"]
    assert r["bas"] >= 1 and r["points_ms"] > 0 and r["lines_ms"] > 0
    assert f"| lb | {r['bas']} |" in text and "Back-end cost of lines" in text
    plain = Pipeline(PipelineConfig.load(ROOT / "configs/synthetic.yaml", {
        "dataset": {"synthetic": {"scene": "corridor", "n_movers": 0, "n_frames": 45}},
        "slam": {"lines": {"enabled": True}}, "output": {"dir": str(tmp_path / "plain")}})).run()
    assert r["ate_rmse"] == plain.eval.ate.translation.rmse
