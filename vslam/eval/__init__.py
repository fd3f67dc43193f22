"""Trajectory evaluation the way the literature does it.

ATE and RPE through evo (numbers equal ``evo_ape``/``evo_rpe``), the KITTI
devkit's odometry metric (t_rel %, r_rel deg/100 m), and self-contained
Markdown/HTML reports with plots.

    from vslam.eval import EvalConfig, evaluate_files, write_report
    res = evaluate_files("est.txt", "gt.txt", EvalConfig(max_diff=0.01))
    write_report(res, "out/eval")
"""

from vslam.eval.associate import Association, associate
from vslam.eval.config import EvalConfig
from vslam.eval.evaluate import evaluate, evaluate_files
from vslam.eval.kitti import KittiLengthError, KittiOdometryError, kitti_odometry_error
from vslam.eval.metrics import Alignment, AteStats, ErrorStats, RpeSeries, RpeStats
from vslam.eval.report import write_report
from vslam.eval.result import EvalArrays, EvalResult

__all__ = [
    "Alignment",
    "Association",
    "AteStats",
    "ErrorStats",
    "EvalArrays",
    "EvalConfig",
    "EvalResult",
    "KittiLengthError",
    "KittiOdometryError",
    "RpeSeries",
    "RpeStats",
    "associate",
    "evaluate",
    "evaluate_files",
    "kitti_odometry_error",
    "write_report",
]
