"""Bench kind ``sfm`` (vslam against offline SfM): its metrics on constructed trajectories, the camera model
handed to COLMAP, the cache, and its table."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.bench.kinds import sfm
from vslam.bench.suite import BenchRow
from vslam.data.trajectory import Trajectory
from vslam.data.types import PinholeCamera
from vslam.eval import EvalConfig
from vslam.geometry.se3 import make_T, so3_exp


def _drive(n: int = 90) -> Trajectory:
    """A curving 0.5 m/frame drive (T_world_cam), 10 Hz."""
    t = np.arange(n) * 0.1
    poses = [make_T(so3_exp([0.0, 0.01 * i, 0.0]), [3.0 * np.sin(0.01 * i) * i / 6, 0.1 * np.sin(0.2 * i), 0.5 * i])
             for i in range(n)]
    return Trajectory(t, np.array(poses))


def _similar(traj: Trajectory, s: float) -> Trajectory:
    """The trajectory in another frame and scale (what a monocular run gives)."""
    T = make_T(so3_exp([0.3, -0.2, 0.1]), [1.0, 2.0, -3.0])
    poses = np.array([T @ p for p in traj.poses])
    poses[:, :3, 3] *= s
    return Trajectory(traj.timestamps, poses)


def test_metrics_of_an_exact_similar_trajectory():
    gt = _drive()
    m = sfm._metrics(_similar(gt, 0.2), gt, EvalConfig(), (10.0, 20.0), 10, "vslam")
    assert m["vslam_ate"] < 1e-9 and m["vslam_t_rel"] < 1e-6 and m["vslam_r_rel"] < 1e-3
    assert m["vslam_scale"] == pytest.approx(5.0)
    assert m["vslam_scale_thirds"] == pytest.approx([1.0, 1.0, 1.0]) and m["scale_jump"] < 1e-9


def test_a_scale_jump_in_the_last_third_is_reported():
    gt = _drive()
    est = _similar(gt, 1.0)
    pos = est.poses[:, :3, 3].copy()
    # from frame 60 on the estimate moves 30 % farther per frame than the truth
    steps = np.diff(pos, axis=0)
    steps[59:] *= 1.3
    est.poses[1:, :3, 3] = pos[0] + np.cumsum(steps, axis=0)
    m = sfm._metrics(est, gt, EvalConfig(), (10.0, 20.0), 10, "vslam")
    first, second, last = m["vslam_scale_thirds"]
    assert last < 0.9 < first and m["scale_jump"] > 0.1
    assert "scale_jump" not in sfm._metrics(est, gt, EvalConfig(), (10.0,), 10, "sfm")  # vslam's own metric


def test_camera_models():
    assert sfm._camera_model(PinholeCamera(640, 480, 500, 501, 320, 240)) == ("PINHOLE", [500, 501, 320, 240])
    radtan = PinholeCamera(752, 480, 458.6, 457.3, 367.2, 248.4, "radtan", (-0.28, 0.07, 0.0002, 1.8e-5))
    assert sfm._camera_model(radtan) == ("OPENCV", [458.6, 457.3, 367.2, 248.4, -0.28, 0.07, 0.0002, 1.8e-5])
    fish = PinholeCamera(640, 480, 300, 300, 320, 240, "equidistant", (0.1, 0.01))
    assert sfm._camera_model(fish)[0] == "OPENCV_FISHEYE" and len(sfm._camera_model(fish)[1]) == 8


def _cfg(**dataset):
    from vslam.pipeline import PipelineConfig

    return PipelineConfig.load(None, {"dataset": {"kind": "synthetic", "sensor": "mono", "synthetic": {"n_frames": 6},
                                                  **dataset}})


def test_cache_keys_and_shared_database(tmp_path, monkeypatch):
    """A result is read back without running SfM; metric options share the key, SfM settings and frame
    selections do not; a later start maps from the whole recording's database, restricted to its frames."""
    gt = _drive(6)
    databases, mapped = [], []

    def fake_database(dataset, opts, folder):
        databases.append(folder.name)
        return {f"{i:06d}.png": float(t) for i, t in enumerate(gt.timestamps)}

    def fake_map(db, names, stamps, opts, folder):
        mapped.append((db.parent.name, folder.name, names))
        idx = [int(n[:6]) for n in names]
        return gt.subset(np.array(idx)), {"frames": len(names), "registered": len(names)}

    monkeypatch.setattr(sfm, "_database", fake_database)
    monkeypatch.setattr(sfm, "_map", fake_map)
    a, info_a = sfm.sfm_reference(_cfg(), sfm.SfmOptions(), tmp_path)
    b, info_b = sfm.sfm_reference(_cfg(), sfm.SfmOptions(rel_lengths=(5.0,)), tmp_path)  # metric options: same key
    assert len(mapped) == 1 and not info_a["cached"] and info_b["cached"]
    np.testing.assert_allclose(b.poses, gt.poses, atol=1e-6)
    sfm.sfm_reference(_cfg(), sfm.SfmOptions(overlap=5), tmp_path)  # another SfM setting: another key
    later, _ = sfm.sfm_reference(_cfg(drop=[[0, 1]]), sfm.SfmOptions(), tmp_path)  # a later start
    gap, _ = sfm.sfm_reference(_cfg(drop=[[2, 3]]), sfm.SfmOptions(), tmp_path)  # a gap: frames of its own
    assert len(mapped) == 4 and len({m[1] for m in mapped}) == 4
    whole = mapped[0][0]
    assert mapped[2][0] == whole and mapped[2][2] == [f"{i:06d}.png" for i in range(2, 6)]  # the whole's database
    assert mapped[3][0] == mapped[3][1] != whole and mapped[3][2] == [f"{i:06d}.png" for i in (0, 1, 4, 5)]
    np.testing.assert_allclose(later.timestamps, gt.timestamps[2:])
    assert sfm._key(_cfg().dataset, sfm.SfmOptions()) == whole


def test_table():
    row = BenchRow(name="x-sfm", kind="sfm", target="t")
    r = {"frames": 10, "frames_read": 10, "ate_rmse": 0.3, "sfm_ate": 0.15, "sfm_ratio": 2.0, "vslam_t_rel": 1.5,
         "vslam_r_rel": 0.2, "sfm": {"registered": 10}, "vslam_scale_thirds": [0.9, 1.0, 1.1], "rel_lengths": [20.0],
         "ms_per_frame": 70.0}
    lines = sfm.table([(row, r), (BenchRow(name="y", kind="sfm"), {"error": "boom"})])
    text = "\n".join(lines)
    assert "| x-sfm | 10 (10) | 0.3000 | 0.1500 | **2.00x** | 1.50 % / 0.20° | – | 20 | 0.900, 1.000, 1.100 | 70.0 | t |" in text
    assert "**failed**: boom" in text


def test_a_reference_that_breaks_its_own_scale_gives_no_ratio():
    ok = sfm.reference_check({"ate_rmse": 0.3, "sfm_ate": 0.15, "sfm_ratio": 2.0, "sfm_scale_thirds": [1.05, 0.98, 0.97]}, 0.1)
    assert ok["sfm_ratio"] == 2.0 and "sfm_invalid" not in ok
    bad = sfm.reference_check({"ate_rmse": 0.3, "sfm_ate": 7.7, "sfm_ratio": 0.04, "sfm_scale_thirds": [2.9, 0.8, 0.9]}, 0.1)
    assert bad["sfm_ratio"] is None and "2.90" in bad["sfm_invalid"]
    assert "not a reference" in "\n".join(sfm.table([(BenchRow(name="k", kind="sfm"), {**bad, "frames": 1})]))
