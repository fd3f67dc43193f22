"""Entry points: evaluate an estimated trajectory against ground truth."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from vslam.data.trajectory import FORMATS, Trajectory, guess_format, kitti_times_path, read_trajectory
from vslam.errors import DatasetError, EvalError
from vslam.eval.associate import associate
from vslam.eval.config import EvalConfig
from vslam.eval.kitti import kitti_odometry_error
from vslam.eval.metrics import DeltaNotApplicable, RpeSeries, RpeStats, align, ate, rpe
from vslam.eval.result import EvalArrays, EvalResult

logger = logging.getLogger(__name__)

# A metric run (RGB-D, stereo, scaled VIO) whose Sim3 scale against the ground truth is off by more than this
# has a unit or calibration wrong (depth in mm read as 1/5000 m gives 5x); good runs fit far closer
# (docs/data.md, "Scale check"). Judged only where the scale is observable: the ground truth spreads over
# SCALE_MIN_SPREAD_M and over SCALE_SPREAD_PER_ATE times the Sim3-aligned ATE (a nearly still camera fits any scale).
SCALE_WARN = 0.10
SCALE_MIN_SPREAD_M = 0.2
SCALE_SPREAD_PER_ATE = 20.0


def evaluate(
    est: Trajectory,
    gt: Trajectory,
    cfg: EvalConfig | None = None,
    monocular: bool = False,
    *,
    by_index: bool = False,
    seconds: bool = True,
    est_path: str | Path | None = None,
    gt_path: str | Path | None = None,
) -> EvalResult:
    """ATE, RPE and the KITTI odometry metric of ``est`` against ``gt``.

    est, gt: T_world_cam trajectories, metres; timestamps in seconds.
    monocular: decides ``align="auto"`` (sim3 when True, else se3).
    by_index: match poses line by line instead of by timestamp (KITTI pose
        files without times). seconds: False when the timestamps are only line
        indices; then durations are in frames and ``seconds`` RPE deltas are dropped.
    est_path, gt_path: only recorded in the result and used in messages.
    """
    cfg = cfg or EvalConfig()
    est_name = Path(est_path).name if est_path else "the estimate"
    gt_name = Path(gt_path).name if gt_path else "the ground truth"
    assoc = associate(est, gt, cfg.max_diff, by_index=by_index, est_name=est_name, gt_name=gt_name)
    method = cfg.resolve_align(monocular)
    alignment, gt_evo, est_evo = align(assoc, method)
    ate_stats, ate_t, ate_r = ate(gt_evo, est_evo)

    notes: list[str] = []
    if by_index:
        notes.append("poses matched line by line (KITTI pose files without timestamps)")
    rpe_stats: list[RpeStats] = []
    rpe_series: dict[str, RpeSeries] = {}
    for value, unit in cfg.rpe_deltas:
        try:
            stats, series = rpe(gt_evo, est_evo, value, unit, seconds=seconds)
        except DeltaNotApplicable as e:
            notes.append(str(e))
            logger.info("%s", e)
            continue
        rpe_stats.append(stats)
        rpe_series[stats.label] = series

    scale_fit, scale_warning = _scale_check(assoc, method, monocular)
    if scale_warning:
        notes.append(scale_warning)
        logger.warning("%s", scale_warning)

    kitti, kitti_reason = kitti_odometry_error(assoc.gt.poses, assoc.est.poses, cfg.kitti_lengths, cfg.kitti_step)
    if method == "se3" and monocular:
        notes.append("SE3 alignment of a trajectory without metric scale (monocular): its scale error counts in the "
                     "ATE; align: auto scores such runs with Sim3")
    if kitti is not None and method == "sim3":
        notes.append("KITTI metric uses the unaligned estimate (as the devkit does), so a scale error counts in full")

    t = assoc.gt.timestamps
    est_xyz = np.asarray(est_evo.positions_xyz, dtype=np.float64)
    result = EvalResult(
        config=cfg,
        est_path=str(est_path) if est_path is not None else None,
        gt_path=str(gt_path) if gt_path is not None else None,
        monocular=monocular,
        alignment=alignment,
        ate=ate_stats,
        rpe=rpe_stats,
        kitti=kitti,
        kitti_reason=kitti_reason,
        n_est=len(est),
        n_gt=len(gt),
        n_matched=len(assoc),
        matched_by="index" if by_index else "time",
        time_unit="s" if seconds else "frame",
        duration=float(t[-1] - t[0]),
        gt_length_m=assoc.gt.path_length(),
        est_length_m=float(np.linalg.norm(np.diff(est_xyz, axis=0), axis=1).sum()),
        notes=notes,
        scale_fit=scale_fit,
        scale_warning=scale_warning,
        arrays=EvalArrays(t=t, gt_xyz=assoc.gt.positions.copy(), est_xyz=est_xyz, ate_t=ate_t, ate_r=ate_r, rpe=rpe_series),
    )
    logger.info("%s", result.summary())
    return result


def _scale_check(assoc, method: str, monocular: bool) -> tuple[float | None, str]:
    """(Sim3 scale of an SE3-scored metric run, a warning when it is far from 1 where the scale is observable)."""
    if method != "se3" or monocular or len(assoc) < 3:
        return None, ""
    try:
        fit, gt_evo, est_evo = align(assoc, "sim3")
    except EvalError:
        return None, ""
    s = fit.s
    sim3_rmse = ate(gt_evo, est_evo)[0].translation.rmse
    gt_xyz = np.asarray(gt_evo.positions_xyz)
    spread = float(np.sqrt(np.mean(np.sum((gt_xyz - gt_xyz.mean(axis=0)) ** 2, axis=1))))
    if abs(s - 1.0) <= SCALE_WARN or spread < max(SCALE_MIN_SPREAD_M, SCALE_SPREAD_PER_ATE * sim3_rmse):
        return s, ""
    return s, (f"the trajectory is {1.0 / s:.3f}x the size of the ground truth (Sim3 scale {s:.3f}) although the run "
               "is metric: check the depth unit (depth scale), the stereo baseline or the camera calibration")


def evaluate_files(
    est_path: str | Path,
    gt_path: str | Path,
    cfg: EvalConfig | None = None,
    est_format: str = "auto",
    gt_format: str = "auto",
    monocular: bool = False,
    *,
    est_times: str | Path | None = None,
    gt_times: str | Path | None = None,
) -> EvalResult:
    """``evaluate`` on two trajectory files (tum, kitti, euroc; ``auto`` guesses).

    KITTI pose files have no timestamps: give ``*_times`` (one time per line)
    to associate by time, else a KITTI file is matched with the other line by
    line, as ``evo_ape kitti`` and the devkit do -- only when both have as many
    rows (else EvalError: the rows would be different frames). ``vslam run``
    writes the times of its KITTI file beside it (``kitti_times_path``): they are
    read when no ``est_times`` is given, and such a file (the frames a run posed)
    is never matched by line. User mistakes (missing file,
    unknown format, no overlap) raise DatasetError/EvalError with one line.
    """
    est_path, gt_path = Path(est_path), Path(gt_path)
    est_fmt = _resolve_format(est_path, est_format)
    gt_fmt = _resolve_format(gt_path, gt_format)
    sidecar = None  # the times `vslam run` wrote beside its KITTI file: used when none are given
    if est_fmt == "kitti" and est_times is None and kitti_times_path(est_path).is_file():
        sidecar = est_times = kitti_times_path(est_path)
        logger.info("times of %s from %s", est_path.name, sidecar.name)
    est = _read(est_path, est_fmt, est_times)
    gt = _read(gt_path, gt_fmt, gt_times)
    est_untimed = est_fmt == "kitti" and est_times is None
    gt_untimed = gt_fmt == "kitti" and gt_times is None
    by_index = est_untimed or gt_untimed
    if by_index and not (est_fmt == gt_fmt == "kitti"):
        untimed, other = (est_path, gt_fmt) if est_untimed else (gt_path, est_fmt)
        raise EvalError(
            f"{untimed.name} is a KITTI pose file without timestamps and the other file is {other}; "
            "give its times file to match by time (vslam eval --times FILE for the estimate, --gt-times FILE "
            "for the ground truth)"
        )
    if sidecar is not None and gt_untimed:
        # a run's KITTI file holds the frames it posed, not every frame: its rows are not the ground truth's
        raise EvalError(
            f"{est_path.name} holds the frames the run posed (a monocular start and lost frames have no row), so its "
            f"rows are not {gt_path.name}'s frames; match by time: give the ground truth's times (--gt-times FILE, "
            f"KITTI's times.txt; the estimate's are read from {sidecar.name})")
    # Two KITTI files where only one has times: match by line, use those times as the time axis.
    seconds = not (est_untimed and gt_untimed)
    if by_index and gt_untimed and not est_untimed and len(est) == len(gt):
        gt = Trajectory(est.timestamps, gt.poses)
    return evaluate(est, gt, cfg, monocular, by_index=by_index, seconds=seconds, est_path=est_path, gt_path=gt_path)


def _resolve_format(path: Path, fmt: str) -> str:
    if fmt == "auto":
        try:
            return guess_format(path)
        except OSError as e:
            raise DatasetError(path, f"cannot read trajectory file ({e.strerror or e})") from None
    if fmt not in FORMATS:
        raise EvalError(f"{path.name}: unknown trajectory format {fmt!r}; expected auto, {', '.join(FORMATS)}")
    return fmt


def _read(path: Path, fmt: str, times: str | Path | None) -> Trajectory:
    try:
        return read_trajectory(path, fmt, times=times)
    except OSError as e:
        raise DatasetError(path, f"cannot read trajectory file ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise DatasetError(path, "not a text file") from None
