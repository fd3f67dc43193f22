"""ATE/RPE/association: exact answers on synthetic data, and equality with the evo CLIs on real data."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from evo.core.result import Result

from tests.eval._synth import curvy, line, transformed
from vslam.data.trajectory import Trajectory, write_trajectory
from vslam.errors import ConfigError, DatasetError, EvalError, VslamError
from vslam.eval import EvalConfig, evaluate, evaluate_files
from vslam.geometry.se3 import make_T, so3_exp

NO_RPE = EvalConfig(rpe_deltas=())


# --- alignment and ATE -------------------------------------------------------------------------


def test_rigid_offset_vanishes_with_se3_and_shows_without_alignment():
    gt = curvy()
    T = make_T(so3_exp([0.1, -0.2, 0.3]), [1.0, 2.0, -3.0])
    res = evaluate(transformed(gt, T), gt, EvalConfig(align="se3"))
    assert res.alignment.method == "se3" and res.alignment.s == 1.0
    assert res.ate.translation.rmse < 1e-9 and res.ate.translation.max < 1e-9
    assert res.ate.rotation_deg.max < 1e-6
    # Alignment maps the estimate onto GT, i.e. it is the inverse of T.
    np.testing.assert_allclose(res.alignment.R, T[:3, :3].T, atol=1e-9)
    np.testing.assert_allclose(res.alignment.t, -T[:3, :3].T @ T[:3, 3], atol=1e-9)

    offset = np.array([0.3, -0.4, 1.2])  # |offset| = 1.3
    res = evaluate(transformed(gt, make_T(np.eye(3), offset)), gt, EvalConfig(align="none"))
    assert res.ate.translation.rmse == pytest.approx(1.3, abs=1e-12)
    assert res.ate.translation.std == pytest.approx(0.0, abs=1e-12)
    assert res.ate.translation.n == len(gt)


def test_sim3_recovers_scale_and_removes_the_error():
    gt = curvy()
    est = transformed(gt, make_T(so3_exp([0.0, 0.4, -0.1]), [5.0, 0.0, 1.0]), scale=0.5)
    est_before = est.poses.copy()
    res = evaluate(est, gt, EvalConfig(align="sim3"))
    np.testing.assert_array_equal(est.poses, est_before)  # the caller's trajectory is not aligned in place
    assert res.alignment.s == pytest.approx(2.0, abs=1e-9)
    assert res.ate.translation.rmse < 1e-9
    assert evaluate(est, gt, EvalConfig(align="se3")).ate.translation.rmse > 0.5


def test_auto_alignment_follows_monocular():
    gt = curvy()
    est = transformed(gt, np.eye(4), scale=0.5)
    assert evaluate(est, gt, NO_RPE, monocular=True).alignment.method == "sim3"
    assert evaluate(est, gt, NO_RPE, monocular=False).alignment.method == "se3"
    assert EvalConfig(align="none").resolve_align(True) == "none"


# --- RPE -------------------------------------------------------------------------------------


def test_rpe_of_constant_velocity_with_known_per_frame_error():
    gt = line(101, step=1.0, dt=0.1)
    est = line(101, step=1.1, dt=0.1)  # 0.1 m too far every frame
    cfg = EvalConfig(align="none", rpe_deltas=((1, "frames"), (2, "frames"), (2.0, "meters"), (0.3, "seconds")))
    res = evaluate(est, gt, cfg)
    assert [(r.delta, r.unit) for r in res.rpe] == [(1, "frames"), (2, "frames"), (2.0, "meters"), (0.3, "seconds")]
    expected = {"frames1": (0.1, 100), "frames2": (0.2, 50), "meters2": (0.2, 50), "seconds0.3": (0.3, 33)}
    for r in res.rpe:
        err, n = expected[f"{r.unit}{r.delta:g}"]
        for v in (r.translation.rmse, r.translation.mean, r.translation.median, r.translation.max, r.translation.min):
            assert v == pytest.approx(err, abs=1e-9)
        assert r.translation.n == n
        assert r.rotation_deg.max == pytest.approx(0.0, abs=1e-9)
    assert res.rpe[3].frames == 3  # 0.3 s / 0.1 s median timestep
    assert res.rpe[3].label == "0.3 seconds (= 3 frames)"
    # ATE without alignment grows linearly: 0.1 * i.
    assert res.ate.translation.mean == pytest.approx(0.1 * 50, abs=1e-9)
    assert res.ate.translation.max == pytest.approx(10.0, abs=1e-9)


def test_too_long_delta_is_dropped_with_a_note():
    gt = curvy(n=30)
    res = evaluate(gt, gt, EvalConfig(rpe_deltas=((1, "frames"), (1000.0, "meters"), (500, "frames"))))
    assert [r.unit for r in res.rpe] == ["frames"]
    assert any("1000 meters skipped" in n for n in res.notes)
    assert any("500 frames skipped" in n for n in res.notes)


def test_seconds_delta_is_dropped_without_timestamps():
    gt = curvy(n=30)
    res = evaluate(gt, gt, EvalConfig(), by_index=True, seconds=False)
    assert "seconds" not in [r.unit for r in res.rpe]
    assert any("no timestamps" in n for n in res.notes)
    assert res.time_unit == "frame" and res.matched_by == "index"


# --- association -----------------------------------------------------------------------------


def test_association_tolerates_small_offsets_and_partial_overlap():
    gt = curvy(n=60, dt=0.1)
    est = Trajectory(gt.timestamps + 0.004, gt.poses)
    assert evaluate(est, gt, EvalConfig(max_diff=0.01)).n_matched == 60
    half = gt.subset(np.arange(30, 60))
    res = evaluate(half, gt, EvalConfig(max_diff=0.01))
    assert (res.n_matched, res.n_est, res.n_gt) == (30, 30, 60)


def test_no_overlap_is_a_one_line_error_naming_both_files():
    gt = curvy()
    est = Trajectory(gt.timestamps * 1e9, gt.poses)  # nanoseconds by mistake
    with pytest.raises(EvalError, match="are both in seconds") as e:
        evaluate(est, gt, EvalConfig(), est_path="est.txt", gt_path="gt.txt")
    msg = str(e.value)
    assert "est.txt" in msg and "gt.txt" in msg and "0.02 s" in msg and "\n" not in msg


def test_interleaved_stamps_without_matches_and_too_few_matches():
    gt = curvy(n=60, dt=0.1)
    with pytest.raises(EvalError, match="no timestamps"):
        evaluate(Trajectory(gt.timestamps + 0.05, gt.poses), gt, EvalConfig(max_diff=0.02))
    with pytest.raises(EvalError, match="only 2 poses"):
        evaluate(gt.subset(np.arange(2)), gt, EvalConfig())


def test_degenerate_alignment_is_an_eval_error():
    gt = curvy(n=10)
    still = Trajectory(gt.timestamps, np.tile(np.eye(4), (10, 1, 1)))
    with pytest.raises(EvalError, match="cannot align.*all 10 estimated positions are the same point"):
        evaluate(still, gt, EvalConfig(align="se3"))


# --- files and user mistakes -----------------------------------------------------------------


def test_evaluate_files_reads_formats_and_reports_user_mistakes(tmp_path):
    gt = curvy()
    est = transformed(gt, make_T(so3_exp([0, 0, 0.2]), [1, 0, 0]))
    write_trajectory(tmp_path / "gt.txt", gt, "tum")
    write_trajectory(tmp_path / "est.csv", est, "euroc")
    write_trajectory(tmp_path / "est_kitti.txt", est, "kitti")
    write_trajectory(tmp_path / "gt_kitti.txt", gt, "kitti")
    write_trajectory(tmp_path / "gt_short_kitti.txt", gt.subset(np.arange(50)), "kitti")
    (tmp_path / "times.txt").write_text("\n".join(f"{t:.6f}" for t in est.timestamps) + "\n")

    res = evaluate_files(tmp_path / "est.csv", tmp_path / "gt.txt", EvalConfig())
    assert res.ate.translation.rmse < 1e-6 and res.matched_by == "time"
    res = evaluate_files(tmp_path / "est_kitti.txt", tmp_path / "gt_kitti.txt", EvalConfig())
    assert res.matched_by == "index" and res.ate.translation.rmse < 1e-6
    res = evaluate_files(tmp_path / "est_kitti.txt", tmp_path / "gt.txt", EvalConfig(), est_times=tmp_path / "times.txt")
    assert res.matched_by == "time" and res.n_matched == len(gt)

    mistakes: list[tuple[dict, type[Exception], str]] = [
        (dict(est_path=tmp_path / "missing.txt"), DatasetError, "missing"),
        (dict(est_format="g2o"), EvalError, "unknown trajectory format 'g2o'"),
        (dict(est_path=tmp_path / "est_kitti.txt"), EvalError, "give its times file"),
        (dict(est_path=tmp_path / "est_kitti.txt", gt_path=tmp_path / "gt_short_kitti.txt"), EvalError, "same length"),
        (dict(est_path=tmp_path), DatasetError, "missing"),
    ]
    (tmp_path / "bad.txt").write_text("1 2 3 4 5\n")
    mistakes.append((dict(est_path=tmp_path / "bad.txt"), DatasetError, "5 columns"))
    for kw, exc, text in mistakes:
        args = {"est_path": tmp_path / "est.csv", "gt_path": tmp_path / "gt.txt", "cfg": EvalConfig(), **kw}
        with pytest.raises(exc, match=text) as e:
            evaluate_files(**args)
        assert isinstance(e.value, VslamError) and "\n" not in str(e.value)


def test_config_rejects_bad_values():
    for kw in (dict(align="sim2"), dict(max_diff=0), dict(rpe_deltas=((1, "hours"),)), dict(rpe_deltas=((1.5, "frames"),)),
               dict(rpe_deltas=((-1.0, "meters"),)), dict(kitti_step=0), dict(kitti_lengths=())):  # fmt: skip
        with pytest.raises(ConfigError):
            EvalConfig(**kw)
    cfg = EvalConfig(rpe_deltas=[[2.0, "frames"], (0.5, "meters")])  # YAML gives lists
    assert cfg.rpe_deltas == ((2, "frames"), (0.5, "meters"))
    assert EvalConfig.from_dict(cfg.to_dict()) == cfg


# --- equality with the evo command-line tools ------------------------------------------------


def _evo_cli(tool: str, args: list[str], tmp_path: Path) -> Result:
    """Run evo_ape/evo_rpe with a throw-away HOME (evo writes ~/.evo) and return its saved result."""
    from evo.tools import file_interface

    exe = Path(sys.executable).with_name(tool)
    cmd = str(exe) if exe.exists() else shutil.which(tool)
    if cmd is None:
        pytest.skip(f"{tool} not installed")
    home = tmp_path / "home"
    home.mkdir(exist_ok=True)
    out = tmp_path / f"{tool}_{len(list(tmp_path.glob('*.zip')))}.zip"
    env = dict(os.environ, HOME=str(home), MPLBACKEND="Agg")
    proc = subprocess.run([cmd, *args, "--save_results", str(out), "--no_warnings"], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return file_interface.load_res_file(out)


STAT_KEYS = ("rmse", "mean", "median", "std", "min", "max")

APE_CASES = [
    ("tum", "freiburg1_xyz-rgbdslam.txt", "freiburg1_xyz-groundtruth.txt", "-a", "se3"),
    ("kitti", "KITTI_00_ORB.txt", "KITTI_00_gt.txt", "-a", "se3"),
    ("tum", "freiburg1_xyz-rgbdslam.txt", "freiburg1_xyz-groundtruth.txt", "-as", "sim3"),
    ("kitti", "KITTI_00_ORB.txt", "KITTI_00_gt.txt", "-as", "sim3"),
]


@pytest.mark.realdata
@pytest.mark.parametrize("fmt,est,gt,flag,align", APE_CASES)
def test_ate_equals_evo_ape_cli(evo_traj_dir, tmp_path, fmt, est, gt, flag, align):
    est_p, gt_p = evo_traj_dir / est, evo_traj_dir / gt
    # evo_ape's default --t_max_diff is 0.01 s.
    ours = evaluate_files(est_p, gt_p, EvalConfig(align=align, max_diff=0.01, rpe_deltas=()))
    theirs = _evo_cli("evo_ape", [fmt, str(gt_p), str(est_p), flag], tmp_path)
    for k in STAT_KEYS:
        assert getattr(ours.ate.translation, k) == pytest.approx(theirs.stats[k], abs=1e-6), k
    sim3 = theirs.np_arrays["alignment_transformation_sim3"]
    assert ours.alignment.s == pytest.approx(np.cbrt(np.linalg.det(sim3[:3, :3])), abs=1e-6)
    np.testing.assert_allclose(ours.alignment.t, sim3[:3, 3], atol=1e-6)


@pytest.mark.realdata
def test_ate_rotation_equals_evo_ape_cli(evo_traj_dir, tmp_path):
    est_p, gt_p = evo_traj_dir / "freiburg1_xyz-rgbdslam.txt", evo_traj_dir / "freiburg1_xyz-groundtruth.txt"
    ours = evaluate_files(est_p, gt_p, EvalConfig(align="se3", max_diff=0.01, rpe_deltas=()))
    theirs = _evo_cli("evo_ape", ["tum", str(gt_p), str(est_p), "-a", "-r", "angle_deg"], tmp_path)
    for k in STAT_KEYS:
        assert getattr(ours.ate.rotation_deg, k) == pytest.approx(theirs.stats[k], abs=1e-6), k


RPE_CASES = [
    (["-d", "1", "-u", "f", "-r", "trans_part"], (1, "frames"), "translation"),
    (["-d", "1", "-u", "f", "-r", "angle_deg"], (1, "frames"), "rotation_deg"),
    (["-d", "0.5", "-u", "m", "-r", "trans_part"], (0.5, "meters"), "translation"),
]


@pytest.mark.realdata
@pytest.mark.parametrize("flags,delta,part", RPE_CASES)
def test_rpe_equals_evo_rpe_cli(evo_traj_dir, tmp_path, flags, delta, part):
    est_p, gt_p = evo_traj_dir / "freiburg1_xyz-rgbdslam.txt", evo_traj_dir / "freiburg1_xyz-groundtruth.txt"
    ours = evaluate_files(est_p, gt_p, EvalConfig(align="se3", max_diff=0.01, rpe_deltas=(delta,)))
    theirs = _evo_cli("evo_rpe", ["tum", str(gt_p), str(est_p), "-a", *flags], tmp_path)
    stats = getattr(ours.rpe[0], part)
    for k in STAT_KEYS:
        assert getattr(stats, k) == pytest.approx(theirs.stats[k], abs=1e-6), k


def test_a_metric_run_at_the_wrong_scale_is_warned_about():
    """Depth in the wrong unit gives a metric run the wrong scale; SE3 then hides it in a larger ATE. The Sim3 scale
    beside the SE3 score says it (0.2: millimetres read as 1/5000 m); a right scale, a monocular run (Sim3 anyway)
    and a camera that hardly moves (any scale fits) are not warned about."""
    from tests.eval._synth import curvy, transformed
    from vslam.eval import evaluate

    gt = curvy()
    wrong = evaluate(transformed(gt, np.eye(4), scale=0.2), gt, EvalConfig(align="se3"))
    assert wrong.scale_fit == pytest.approx(5.0, rel=1e-6)  # evo's s: the estimate is scaled by s onto the truth
    assert "the trajectory is 0.200x the size of the ground truth" in wrong.scale_warning
    assert wrong.scale_warning in wrong.notes and wrong.to_dict()["scale_warning"] == wrong.scale_warning
    right = evaluate(transformed(gt, np.eye(4), scale=1.03), gt, EvalConfig(align="se3"))
    assert right.scale_fit == pytest.approx(1 / 1.03, rel=1e-6) and right.scale_warning == ""
    mono = evaluate(transformed(gt, np.eye(4), scale=0.2), gt, monocular=True)
    assert mono.alignment.method == "sim3" and mono.scale_fit is None and mono.scale_warning == ""
    still = curvy(length_scale=0.01)  # a few centimetres of motion
    assert evaluate(transformed(still, np.eye(4), scale=0.5), still, EvalConfig(align="se3")).scale_warning == ""


def test_a_runs_kitti_file_is_matched_by_its_times_never_by_row(tmp_path):
    """A monocular run poses none of the frames before its map exists, so its KITTI file (no time column) has fewer
    rows than the ground truth has frames; matched line by line it pairs every pose with another frame (0.115 vs
    0.076 m on KITTI 07). The run writes the rows' times beside it: ``vslam eval`` reads them, and refuses a
    ground truth without times instead of matching rows."""
    from vslam.data.trajectory import TrajectoryWriter, kitti_times_path
    from vslam.eval import evaluate_files

    gt = curvy()
    with TrajectoryWriter(tmp_path / "trajectory.kitti.txt", "kitti") as w:
        for t, T in zip(gt.timestamps[5:], gt.poses[5:]):  # the first 5 frames had no pose
            w.write(t, T)
    times = kitti_times_path(tmp_path / "trajectory.kitti.txt")
    assert times.name == "trajectory.kitti.times.txt" and len(times.read_text().split()) == len(gt) - 5
    write_trajectory(tmp_path / "gt_kitti.txt", gt.subset(np.arange(len(gt) - 5)), "kitti")  # as many rows
    (tmp_path / "gt_times.txt").write_text("\n".join(f"{t:.6f}" for t in gt.timestamps[:-5]) + "\n")
    with pytest.raises(EvalError, match="--gt-times"):
        evaluate_files(tmp_path / "trajectory.kitti.txt", tmp_path / "gt_kitti.txt")
    res = evaluate_files(tmp_path / "trajectory.kitti.txt", tmp_path / "gt_kitti.txt", gt_times=tmp_path / "gt_times.txt")
    assert res.matched_by == "time" and res.n_matched == len(gt) - 10 and res.ate.translation.rmse < 1e-5
