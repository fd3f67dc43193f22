"""The two-view pose benchmark's pieces on exact synthetic geometry: the pose convention matches what
``recoverPose`` estimates, errors are sign-free in translation, the AUC is SuperGlue's."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.errors import ConfigError
from vslam.eval.pose_auc import estimate_pose, format_table, pose_auc, pose_error, relative_pose, standard_methods


def _rot(axis, deg):
    import cv2

    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(deg))[0]


def test_estimate_pose_recovers_the_ground_truth_convention():
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    T_w1, T_w2 = np.eye(4), np.eye(4)
    T_w2[:3, :3], T_w2[:3, 3] = _rot([0.2, 1, 0.1], 4.0), [0.3, 0.05, 0.1]
    pts_w = np.c_[rng.uniform(-2, 2, (300, 2)), rng.uniform(4, 8, 300)]

    def project(T_wc):
        p = (np.linalg.inv(T_wc) @ np.c_[pts_w, np.ones(len(pts_w))].T)[:3].T
        return (p[:, :2] / p[:, 2:]) * 500.0 + [320, 240]

    x1, x2 = project(T_w1), project(T_w2)
    x2[:60] = rng.uniform(0, 640, (60, 2))  # 20 % outliers
    R_gt, t_gt = relative_pose(T_w1, T_w2)
    R, t = estimate_pose(x1, x2, K, K, 1.0)
    err_r, err_t = pose_error(R, t, R_gt, t_gt)
    assert err_r < 0.1 and err_t < 0.5, (err_r, err_t)
    # the inverse motion (a convention slip) is far off
    assert max(pose_error(R.T, -R.T @ t, R_gt, t_gt)) > 5.0
    assert estimate_pose(x1[:4], x2[:4], K, K, 1.0) is None


def test_translation_error_ignores_sign_and_scale():
    R = _rot([0, 1, 0], 10.0)
    t = np.array([1.0, 0.0, 0.2])
    assert pose_error(R, -3.0 * t, R, t) == pytest.approx((0.0, 0.0), abs=1e-5)
    assert pose_error(R, np.array([0.0, 1.0, 0.0]), R, np.array([1.0, 0.0, 0.0]))[1] == pytest.approx(90.0)
    assert pose_error(_rot([0, 1, 0], 13.0), t, R, t)[0] == pytest.approx(3.0, abs=1e-6)


def test_pose_auc_is_superglues():
    """Errors 0, 5, 15, inf: the recall curve (0,0) (0,1/4) (5,2/4) (15,3/4), linear between points (SuperGlue's
    trapezoids), cut at the threshold. Up to 5: 1/4 * 5 = 1.25 -> 0.25; up to 10: 1.875 + 2.5 -> 0.4375; up to 20:
    1.875 + 6.25 + 3.75 -> 0.59375."""
    np.testing.assert_allclose(pose_auc([0.0, 5.0, 15.0, np.inf], (5.0, 10.0, 20.0)), [0.25, 0.4375, 0.59375])
    assert pose_auc([np.inf] * 3, (5.0,)) == [0.0]


def test_unknown_method_is_one_line():
    with pytest.raises(ConfigError, match="unknown method 'surf'"):
        standard_methods(100, ("orb", "surf"))


def test_alike_method_on_onnxruntime_gives_torch_keypoints():
    """"alike-t@0.5+onnxruntime": the same network with its dense part in onnxruntime, the same keypoints."""
    pytest.importorskip("onnxruntime")
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.standard_normal((240, 320)).astype(np.float32), (0, 0), 2.0)
    img = ((img - img.min()) / (img.max() - img.min()) * 255).astype(np.uint8)
    m = standard_methods(300, ("alike-t@0.5", "alike-t@0.5+onnxruntime"))
    (xa, da), (xb, db) = m["alike-t@0.5"](img), m["alike-t@0.5+onnxruntime"](img)
    assert len(xa) == len(xb) > 100
    same = np.linalg.norm(xa - xb, axis=1) < 1e-3  # near-equal scores may swap places in the order
    assert same.mean() > 0.95 and (da[same] * db[same]).sum(1).min() > 0.9999


def test_table_lists_every_method_and_set():
    res = {"kitti_k1": {"orb": {"auc@5": 40.0, "auc@10": 60.0, "auc@20": 80.0}},
           "ms": {"kitti": {"orb": 9.6}}, "n_keypoints": 2000, "ransac_px": 1.0, "threads": 1, "seconds": 3.0}
    assert format_table(res)[-1] == "| orb | 40/60/80 | 10 |"


def test_bench_kind_on_real_pairs():
    """The `pose` bench kind end to end on a few real pairs: consecutive KITTI 07 frames are an easy pose (ORB's
    AUC@20 on them is ~85 over 50 pairs); a wrong pose convention, intrinsics or matching gives ~0."""
    from vslam.bench import execute_job
    from vslam.paths import data_root

    if not (data_root() / "kitti/sequences/07").exists():
        pytest.skip(f"{data_root() / 'kitti/sequences/07'} not found (set VSLAM_DATA)")
    res = execute_job("pose", None, {"methods": ["orb"], "pairs": 4, "threads": 1}, "")
    k1 = res["kitti_k1"]["orb"]
    assert k1["pairs"] == 4 and k1["failed"] == 0 and k1["matches"] > 300
    assert k1["auc@20"] > 50.0, k1
    assert res["ms"]["kitti"]["orb"] > 0 and res["threads"] == 1
