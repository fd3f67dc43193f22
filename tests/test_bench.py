"""`vslam bench` writes BENCHMARKS.md rows from real runs in fresh processes."""

from __future__ import annotations

import pytest

import json
from pathlib import Path

from vslam.bench import load_sidecar, load_suite, run_bench
from vslam.bench.kinds.run import stage_times
from vslam.errors import ConfigError, DatasetError

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
    from vslam.bench.run import _composited

    with pytest.raises(ConfigError, match="needs 'data'"):
        _composited({"people": 2}, tmp_path)
    with pytest.raises(ConfigError, match="takes people, seed .seeds: kind ab., coco"):
        _composited({"data": "tum/x", "walkers": 2}, tmp_path)
    from vslam.data.composite import GENERATOR_VERSION

    stale = tmp_path / "_data" / f"x-people2-seed1-v{GENERATOR_VERSION - 1}"  # another generator's frames
    done = tmp_path / "_data" / f"x-people2-seed1-v{GENERATOR_VERSION}"
    for d in (stale, done):
        d.mkdir(parents=True)
        (d / "boxes.txt").write_text("# already composited\n")  # written last, once, then reused as it is
    assert _composited({"data": "tum/x", "people": 2, "seed": 1}, tmp_path) == ("tum", done.resolve())
    done.joinpath("boxes.txt").unlink()  # not this generator's: made again (here: no such data folder)
    with pytest.raises(DatasetError):
        _composited({"data": "tum/x", "people": 2, "seed": 1}, tmp_path)


def test_ab_rows_over_composites_run_one_grid_point_per_walker_seed(tmp_path, monkeypatch):
    """make_dynamic seeds: A and B run on each seed's composite (same folder for both), the table names seeds."""
    import vslam.bench.batch
    import vslam.bench.run

    monkeypatch.setattr(vslam.bench.run, "_composited", lambda spec, jobs_dir: ("tum", tmp_path / f"walkers-{spec['seed']}"))
    seen = []

    def fake_run_jobs(jobs, workers, ray, progress=None):
        seen.extend(jobs)
        return [{"ate_rmse": 0.001 * (i + 1)} for i in range(len(jobs))]

    monkeypatch.setattr(vslam.bench.batch, "run_jobs", fake_run_jobs)
    suite = tmp_path / "configs" / "suite.yaml"
    suite.parent.mkdir()
    suite.write_text("rows:\n  - name: people-seeds\n    kind: ab\n    config: configs/x.yaml\n"
                     "    set: [slam.dynamic.source=gt_mask]\n    treatment: [slam.dynamic.source=detector]\n"
                     "    make_dynamic: {data: tum/teddy, people: 3, seeds: [0, 7]}\n")
    run_bench(suite, tmp_path / "B.md", jobs_dir=tmp_path / "runs")
    assert [j.overrides["dataset"]["path"] for j in seen] == [str(tmp_path / f"walkers-{s}") for s in (0, 0, 7, 7)]
    assert [j.overrides["slam"]["dynamic"]["source"] for j in seen] == ["gt_mask", "detector"] * 2
    assert {j.overrides["dataset"]["kind"] for j in seen} == {"tum"}
    entry = load_sidecar(tmp_path / "B.json")["people-seeds"]
    assert "commit" in entry  # None here: the suite's folder is not a git checkout
    r = entry["result"]
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


# --- targets as checks (issue 42): parsed from the suite, evaluated on the sidecar as written ---------------------

CHECK_SUITE = """title: t
rows:
  - name: ref
    check:
      - {metric: ate_pct_path, op: "<=", value: 0.5}
      - {metric: untracked, op: "==", value: 0}
    headline: "the reference run"
  - name: variant
    target: "ATE ≤ 1.1x ref; ms/frame vs ref"
    check:
      - {metric: ate_rmse, op: "<=", ratio: 1.1, of: ref}
      - {metric: ms_per_frame, op: "<=", value: 20, open: "issue 41"}
  - name: ab
    kind: ab
    check:
      - {metric: ate_b_mean, op: "<=", ratio: 1.2, of: ref, of_metric: ate_rmse}
      - {metric: mean_ratio, op: "<", value: 1}
  - name: words
    target: "looks right"
    headline: "text only"
  - name: later
    check:
      - {metric: ate_rmse, op: "<=", value: 1}
"""


def _run(ate: float, frames: int = 100, tracked: int = 100, **kw):
    return {"frames": frames, "tracked": tracked, "ate_rmse": ate, "path_m": 2.0, "ms_per_frame": 30.0, "fps": 33.3,
            "peak_rss_mb": 400.0, **kw}


def _sidecar(tmp_path, rows: dict, extra: dict | None = None) -> Path:
    side = tmp_path / "B.json"
    entries = {n: {"result": r, "measured": "2026-12-05 01:00 UTC", "repeat": 1, "machine": "m", **(extra or {}).get(n, {})}
               for n, r in rows.items()}
    side.write_text(json.dumps({"version": 1, "suite": "s", "rows": entries}))
    return side


def _check_suite(tmp_path, text: str = CHECK_SUITE) -> Path:
    suite = tmp_path / "suite.yaml"
    suite.write_text(text)
    return suite


def test_checks_are_parsed_from_the_suite_and_bad_ones_named(tmp_path):
    from vslam.bench.checks import Check, check_text, target_text

    rows = {r.name: r for r in load_suite(_check_suite(tmp_path)).rows}
    assert rows["ref"].check == (Check("ate_pct_path", "<=", value=0.5), Check("untracked", "==", value=0.0))
    assert rows["variant"].check[0] == Check("ate_rmse", "<=", ratio=1.1, of="ref")
    assert rows["variant"].check[1].open == "issue 41" and rows["ref"].headline == "the reference run"
    # the target a reader sees: the row's words, else its checks written out
    assert target_text(rows["variant"]) == "ATE ≤ 1.1x ref; ms/frame vs ref"
    assert target_text(rows["ref"]) == "ATE ≤ 0.5 % of path; frames not tracked = 0"
    assert check_text(rows["ab"].check[0], "ab") == "mean ATE B ≤ 1.2x ref ATE"
    assert check_text(Check("ate_rmse", "<=", of="ref", plus=0.05)) == "ATE ≤ ref + 0.05 m"
    for bad, match in [("{metric: ate_rmse, op: '<='}", "either value or a reference"),
                       ("{metric: ate_rmse, op: '<=', value: 1, of: ref}", "either value or a reference"),
                       ("{metric: ate_rmse, op: '<=', ratio: 2}", "needs `of`"),
                       ("{metric: ate_rmse, op: '~', value: 1}", "op"),
                       ("{metric: ate_rmse, op: '<=', value: 1, bound: 2}", "unknown key 'rows\\[0\\].check\\[0\\].bound'")]:
        with pytest.raises(ConfigError, match=match):
            load_suite(_check_suite(tmp_path, f"rows:\n  - name: x\n    check:\n      - {bad}\n"))


def test_checks_evaluate_values_ratios_to_other_rows_and_paths():
    from vslam.bench.checks import Check, evaluate_check, metric_value, verdict

    entries = {n: {"result": r} for n, r in {
        "ref": _run(0.010),
        "ok": _run(0.0109, align="sim3 (s=1.0150)"),
        "worse": _run(0.0111, frames=100, tracked=97, lost=3, maps={"0": {"frames": 60, "ate_rmse": 0.02},
                                                                     "1": {"frames": 37, "ate_rmse": 0.05}}),
        "ab": {"ate_a": [0.004, 0.006, None], "ate_b": [0.005, 0.007, 0.1], "mean_ratio": 1.2},
        "nested": {"sets": {"TUM fr3/teddy, frames ≥ 100 (≤ 0.3 m)": {"bow": {"r@1": 0.13}, "vladnet": {"r@1": 0.18}}},
                   "models": {"detector_se_gpu.pt": {"ms": 4.5}}, "windows": [{"nees": 5.0}, {"nees": 7.5}]},
        "failed": {"error": "RuntimeError: boom"},
        "gpu": {"skipped": "no CUDA device here"},
    }.items()}
    ratio = Check("ate_rmse", "<=", ratio=1.1, of="ref")
    ok, worse = evaluate_check("ok", ratio, entries), evaluate_check("worse", ratio, entries)
    assert ok.status == "pass" and ok.bound == pytest.approx(0.011) and ok.measured == 0.0109
    assert worse.status == "miss" and "worse: ate_rmse 0.0111 m vs target ≤ 0.0110 m (ATE ≤ 1.1x ref)" == worse.line
    # derived metrics
    assert metric_value(entries["ref"]["result"], "ate_pct_path") == pytest.approx(0.5)
    assert metric_value(entries["worse"]["result"], "untracked") == 3
    assert metric_value(entries["worse"]["result"], "max_map_ate") == 0.05
    assert metric_value(entries["worse"]["result"], "maps_at_end") == 2 and metric_value(entries["ok"]["result"], "maps_at_end") == 1
    assert metric_value(entries["ok"]["result"], "sim3_scale") == 1.015
    assert metric_value(entries["ab"]["result"], "ate_b_mean") == pytest.approx(0.006)  # points where both ran
    # paths: a unique key prefix, a key holding dots, a list index
    assert metric_value(entries["nested"]["result"], "sets.TUM.vladnet.r@1") == 0.18
    assert metric_value(entries["nested"]["result"], "models.detector_se_gpu.pt.ms") == 4.5
    assert metric_value(entries["nested"]["result"], "windows.1.nees") == 7.5
    same_row = Check("sets.TUM.vladnet.r@1", ">=", of_metric="sets.TUM.bow.r@1")
    assert evaluate_check("nested", same_row, entries).status == "pass"
    grown = evaluate_check("worse", Check("ate_rmse", "<=", of="ref", plus=0.0005), entries)  # an allowed growth
    assert grown.bound == pytest.approx(0.0105) and grown.status == "miss"
    assert evaluate_check("worse", Check("ate_rmse", "<=", of="ref", plus=0.002), entries).status == "pass"
    # open: a known miss is not a failure; one that passes again says so
    assert evaluate_check("worse", Check("ate_rmse", "<=", ratio=1.1, of="ref", open="issue 41"), entries).status == "known"
    assert evaluate_check("ok", Check("ate_rmse", "<=", ratio=1.1, of="ref", open="issue 41"), entries).status == "fixed"
    # not measured (row or reference absent, job skipped) is not a miss; a failed job and an unknown number are
    assert evaluate_check("absent", ratio, entries).status == "unmeasured"
    assert evaluate_check("ok", Check("ate_rmse", "<=", of="absent"), entries).status == "unmeasured"
    assert evaluate_check("gpu", Check("ms.detector", "<=", value=5), entries).why == "no CUDA device here"
    failed = evaluate_check("failed", Check("ate_rmse", "<=", value=1), entries)
    assert failed.status == "miss" and "failed: RuntimeError: boom" in failed.line
    typo = evaluate_check("ok", Check("ate_rsme", "<=", value=1), entries)
    assert typo.status == "miss" and "ate_rsme" in typo.why
    assert evaluate_check("nested", Check("sets.synthetic.bow.r@1", ">=", value=0), entries).status == "miss"
    # the row's mark
    outs = [evaluate_check("ok", ratio, entries)]
    assert verdict(outs) == "✓" and verdict([]) == "–" and verdict([worse, *outs]) == "✗"
    known = evaluate_check("worse", Check("ate_rmse", "<=", ratio=1.1, of="ref", open="issue 41"), entries)
    assert verdict([known, *outs]) == "✗ (open)" and verdict([known], why=True) == "✗ (open: issue 41)"


def test_same_pose_checks_allow_a_relative_tolerance_and_say_both_numbers():
    """``~=``: rows that must give another row's poses. The same run measured on two machines (0.0039 vs 0.0041 m,
    5 %) passes a 10 % tolerance; a regression that moves the ATE by a fifth does not."""
    from vslam.bench.checks import Check, check_text, evaluate_check

    entries = {n: {"result": _run(a)} for n, a in {"ref": 0.0039, "other_machine": 0.0041, "regressed": 0.0047,
                                                    "better_by_luck": 0.0033}.items()}
    same = Check("ate_rmse", "~=", of="ref", tol=0.1)
    assert check_text(same) == "ATE ≈ ref (±10 %)"
    assert evaluate_check("other_machine", same, entries).status == "pass"
    missed = evaluate_check("regressed", same, entries)
    assert missed.status == "miss" and missed.line == "regressed: ate_rmse 0.0047 m vs target ≈ 0.0039 m ±10 % (ATE ≈ ref (±10 %))"
    assert evaluate_check("better_by_luck", same, entries).status == "miss"  # different poses, whichever way
    for bad in ({"op": "~=", "of": "ref"}, {"op": "<=", "of": "ref", "tol": 0.1}, {"op": "=~", "of": "ref"}):
        with pytest.raises(ConfigError, match="op"):
            Check("ate_rmse", **bad)


def test_bench_check_exits_1_on_a_miss_and_0_when_every_miss_is_open(tmp_path, capsys):
    from vslam.cli import main

    suite = _check_suite(tmp_path)
    rows = {"ref": _run(0.010), "variant": _run(0.0105), "words": _run(0.5),
            "ab": {"ate_a": [0.012, 0.012], "ate_b": [0.011, 0.011], "mean_ratio": 0.92}}
    _sidecar(tmp_path, rows)
    args = ["bench", "--check", "--suite", str(suite), "--output", str(tmp_path / "B.md")]
    assert main(args) == 1  # "later" is checked but was never measured: a lost or renamed row fails
    out = capsys.readouterr().out
    assert "Not measured:\n  later: ate_rmse (not in BENCHMARKS.json)" in out and "Targets missed" not in out
    assert "1 checked rows have no measurement in BENCHMARKS.json" in out
    rows["later"] = {"skipped": "needs a GPU"}  # a job that was skipped may stay unmeasured
    _sidecar(tmp_path, rows)
    assert main(args) == 0  # variant's 30 ms/frame misses, but its check is open
    out = capsys.readouterr().out
    assert "Known misses (open):\n  variant: ms_per_frame 30.0 vs target ≤ 20.0 (ms/frame ≤ 20); open: issue 41" in out
    assert "7 checks on 4 rows: 5 pass, 0 missed, 1 known misses, 1 not measured" in out
    rows["variant"] = _run(0.0115)  # 1.15x ref: a regression
    rows["ab"]["mean_ratio"] = 1.0
    _sidecar(tmp_path, rows)
    assert main(args) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[:3] == ["Targets missed:", "  variant: ate_rmse 0.0115 m vs target ≤ 0.0110 m (ATE ≤ 1.1x ref)",
                       "  ab: mean_ratio 1 vs target < 1 (mean ATE B / mean ATE A < 1)"]  # equal: more digits
    assert not (tmp_path / "B.md").exists()  # --check writes nothing


def test_render_from_the_sidecar_marks_rows_and_names_their_commit(tmp_path):
    from vslam.bench import render_bench
    from vslam.bench.checks import git_commit

    suite = _check_suite(tmp_path)
    _sidecar(tmp_path, {"ref": _run(0.010), "variant": _run(0.0115), "words": _run(0.5)},
             extra={"ref": {"commit": "1a2b3c4-dirty"}})
    text = render_bench(suite, tmp_path / "B.md").read_text()
    main_rows = {ln.split("|")[1].strip(): ln for ln in text.split("## Targets")[0].splitlines() if ln.startswith("| ")}
    assert main_rows["ref"].endswith("| ✓ ATE ≤ 0.5 % of path; frames not tracked = 0 |")
    assert main_rows["variant"].endswith("| ✗ ATE ≤ 1.1x ref; ms/frame vs ref |")
    assert main_rows["words"].endswith("| looks right |")  # a target in words only: no mark
    targets = {ln.split("|")[1].strip(): ln for ln in text.split("## Targets")[1].split("\n## ")[0].splitlines()
               if ln.startswith("| ") and not ln.startswith("| row")}
    assert targets["ref"] == ("| ref | ATE ≤ 0.5 % of path; frames not tracked = 0 | ATE 0.50 % of path (≤ 0.50 % of path) ✓; "
                              "frames not tracked 0 (= 0) ✓ | ✓ | 2026-12-05 01:00 UTC, 1a2b3c4-dirty |")
    assert "ms/frame 30.0 (≤ 20.0) ✗ open: issue 41 | ✗ | 2026-12-05 01:00 UTC, – |" in targets["variant"]
    assert targets["words"] == "| words | looks right | – | – | 2026-12-05 01:00 UTC, – |"
    assert "Written by `vslam bench` on 2026-12-05 01:00 UTC." in text  # when the sidecar was written, not now
    # the commit a run records: HEAD's short hash, -dirty with uncommitted changes; None outside a repository
    here = git_commit(ROOT)
    assert here is None or __import__("re").fullmatch(r"[0-9a-f]{4,40}(-dirty)?", here)


def test_readme_table_goes_between_the_markers_or_nowhere(tmp_path, caplog):
    from vslam.bench import render_bench

    suite = _check_suite(tmp_path)
    _sidecar(tmp_path, {"ref": _run(0.010), "variant": _run(0.0115), "words": _run(0.5)}, extra={"ref": {"commit": "abc1234"}})
    readme = tmp_path / "README.md"
    before, after = "# x\n\nintro\n\n<!-- bench-table:start -->\n", "<!-- bench-table:end -->\n\nmore\n"
    readme.write_text(before + "| old | table |\n" + after)
    render_bench(suite, tmp_path / "B.md", readme)
    text = readme.read_text()
    assert text.startswith(before) and text.endswith(after) and "| old |" not in text
    table = text[len(before):-len(after)].splitlines()
    assert table[0] == "| row | what it measures | ATE / metric | target | ✓/✗ | measured (date, commit) |"
    assert table[2:] == ["| ref | the reference run | ATE 0.0100 m, 30 ms/frame | ATE ≤ 0.5 % of path; frames not tracked = 0 "
                         "| ✓ | 2026-12-05 01:00 UTC, abc1234 |",
                         "| words | text only | ATE 0.5000 m, 30 ms/frame | looks right | – | 2026-12-05 01:00 UTC, – |"]
    render_bench(suite, tmp_path / "B.md", readme)
    assert readme.read_text() == text  # the same sidecar, the same README
    readme.write_text("# no markers\n")
    render_bench(suite, tmp_path / "B.md", readme)
    assert readme.read_text() == "# no markers\n" and "markers <!-- bench-table:start -->" in caplog.text


def test_the_suite_checks_hold_on_benchmarks_json_as_written():
    """What CI runs (`vslam bench --check`): every check names a number its row records, and no miss but open ones."""
    from vslam.bench import check_bench

    lines, code = check_bench(ROOT / "configs/bench.yaml", ROOT / "BENCHMARKS.md")
    assert code == 0, "\n".join(lines)
    assert lines[-1].endswith(" 0 not measured"), lines[-1]
