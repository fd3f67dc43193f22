"""Report files: JSON round trip, PNGs, Markdown and a self-contained HTML, headless and fast."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from tests.eval._synth import curvy, line, transformed
from vslam.data.trajectory import Trajectory
from vslam.eval import EvalConfig, EvalResult, evaluate, evaluate_files, write_report
from vslam.eval.plots import DPI, FIGSIZE, top_view_axes
from vslam.geometry.se3 import make_T, so3_exp


def _noisy_result(n: int = 1000) -> EvalResult:
    """1000 poses over ~1.5 km with noise and a small rotation drift, so every metric is non-trivial."""
    rng = np.random.default_rng(0)
    gt = curvy(n=n, length_scale=80.0)
    est = transformed(gt, make_T(so3_exp([0.0, 0.0, 0.1]), [2.0, -1.0, 0.5]), scale=0.8)
    est.poses[:, :3, 3] += rng.normal(scale=0.05, size=(n, 3))
    return evaluate(est, gt, EvalConfig(), monocular=True, est_path="est.txt", gt_path="gt.txt")


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


@pytest.fixture
def isolated_home(tmp_path, monkeypatch) -> Path:
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    return home


def test_report_files_are_complete_fast_and_self_contained(tmp_path, isolated_home):
    res = _noisy_result()
    assert res.kitti is not None and res.alignment.method == "sim3"
    t0 = time.perf_counter()
    files = write_report(res, tmp_path / "report", title="Synthetic <run>")
    elapsed = time.perf_counter() - t0
    assert elapsed < 3.0, f"report took {elapsed:.2f} s"

    expected = {"metrics", "report_md", "report_html", "trajectory", "ate_time", "ate_hist", "rpe_time"}
    assert set(files) == expected
    assert all(p.is_file() and p.stat().st_size > 0 for p in files.values())
    for key in ("trajectory", "ate_time", "ate_hist", "rpe_time"):
        assert _png_size(files[key]) == (int(FIGSIZE[0] * DPI), int(FIGSIZE[1] * DPI))

    page = files["report_html"].read_text()
    assert 'src="http' not in page and "http://" not in page and "https://" not in page
    assert page.count("data:image/png;base64,") == 4
    assert "Synthetic &lt;run&gt;" in page  # escaped
    assert "t_rel (%)" in page and "r_rel (deg/100 m)" in page

    md = files["report_md"].read_text()
    assert "![" in md and "(trajectory.png)" in md and "(rpe_time.png)" in md
    assert f"{res.ate.translation.rmse:.6f}" in md
    assert "sim3, scale" in md
    assert not (isolated_home / ".evo").exists()  # plotting never touches evo's settings


def test_metrics_json_round_trips(tmp_path):
    res = _noisy_result(300)
    files = write_report(res, tmp_path, title="x")
    data = json.loads(files["metrics"].read_text())
    assert data == json.loads(json.dumps(res.to_dict()))
    back = EvalResult.from_dict(data)
    assert back.to_dict() == data
    assert back.arrays is None and back.config == res.config
    assert back.ate.translation.rmse == res.ate.translation.rmse
    assert [r.label for r in back.rpe] == [r.label for r in res.rpe]
    np.testing.assert_array_equal(back.alignment.R, res.alignment.R)
    assert "arrays" not in data


def test_report_without_plots_and_from_json(tmp_path):
    res = _noisy_result(200)
    files = write_report(EvalResult.from_dict(res.to_dict()), tmp_path / "a")
    assert set(files) == {"metrics", "report_md", "report_html"}
    assert "data:image" not in files["report_html"].read_text()
    res.config = EvalConfig(plots=False)
    files = write_report(res, tmp_path / "b")
    assert not list((tmp_path / "b").glob("*.png"))


def test_report_explains_missing_kitti_metric_and_notes(tmp_path):
    gt = line(60)
    res = evaluate(Trajectory(gt.timestamps, gt.poses), gt, EvalConfig(align="none", rpe_deltas=((1, "frames"), (1e3, "meters"))))
    assert res.kitti is None
    files = write_report(res, tmp_path)
    md = files["report_md"].read_text()
    assert res.kitti_reason in md and "skipped" in md
    assert "skipped" in files["report_html"].read_text()


def test_top_view_picks_the_ground_plane():
    rng = np.random.default_rng(1)
    kitti_like = np.c_[rng.uniform(-300, 300, 50), rng.uniform(-2, 2, 50), rng.uniform(0, 500, 50)]
    assert top_view_axes(kitti_like) == (0, 2)  # xz: camera y points down
    tum_like = np.c_[rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50), rng.uniform(1, 1.5, 50)]
    assert top_view_axes(tum_like) == (0, 1)


@pytest.mark.realdata
def test_report_on_kitti_00(evo_traj_dir, tmp_path, isolated_home):
    res = evaluate_files(evo_traj_dir / "KITTI_00_ORB.txt", evo_traj_dir / "KITTI_00_gt.txt", EvalConfig())
    files = write_report(res, tmp_path, title="KITTI 00 ORB")
    md = files["report_md"].read_text()
    assert "| duration | 4540.00 frames |" in md and "line by line" in md
    assert f"| all | {res.kitti.t_rel:.4f} | {res.kitti.r_rel:.4f} |" in md
    assert files["trajectory"].is_file() and not (isolated_home / ".evo").exists()
