"""Evaluation the way the literature does it.

Trajectories: ATE and RPE through evo (numbers equal ``evo_ape``/``evo_rpe``), the KITTI devkit's odometry
metric (t_rel %, r_rel deg/100 m), and self-contained Markdown/HTML reports with plots.

    from vslam.eval import EvalConfig, evaluate_files, write_report
    res = evaluate_files("est.txt", "gt.txt", EvalConfig(max_diff=0.01))
    write_report(res, "out/eval")

The networks, apart from the runtime stages that use them: detectors (``detector``: AP on labelled photos;
``detect``: boxes in COCO's results format; ``ablation``: the attention variants side by side), keypoints
(``keypoints``, ``homography``: repeatability and homography accuracy; ``pose_auc``: two-view relative pose;
``extraction_speed``), place descriptors (``place``: recall@k).

Names are resolved lazily (PEP 562): the network tools load with torch, numpy and cv2 alone, without evo.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Association": "associate", "associate": "associate", "EvalConfig": "config", "evaluate": "trajectory",
    "evaluate_files": "trajectory", "KittiLengthError": "kitti", "KittiOdometryError": "kitti",
    "kitti_odometry_error": "kitti", "Alignment": "metrics", "AteStats": "metrics", "ErrorStats": "metrics",
    "RpeSeries": "metrics", "RpeStats": "metrics", "write_report": "report", "EvalArrays": "result",
    "EvalResult": "result",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'vslam.eval' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"vslam.eval.{_EXPORTS[name]}"), name)
    globals()[name] = value  # looked up once
    return value
