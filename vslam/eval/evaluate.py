"""Entry points: evaluate an estimated trajectory against ground truth."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from vslam.data.trajectory import FORMATS, Trajectory, guess_format, read_trajectory
from vslam.errors import DatasetError, EvalError
from vslam.eval.associate import associate
from vslam.eval.config import EvalConfig
from vslam.eval.kitti import kitti_odometry_error
from vslam.eval.metrics import DeltaNotApplicable, RpeSeries, RpeStats, align, ate, rpe
from vslam.eval.result import EvalArrays, EvalResult

logger = logging.getLogger(__name__)


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
        arrays=EvalArrays(t=t, gt_xyz=assoc.gt.positions.copy(), est_xyz=est_xyz, ate_t=ate_t, ate_r=ate_r, rpe=rpe_series),
    )
    logger.info("%s", result.summary())
    return result


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
    line, as ``evo_ape kitti`` and the devkit do. User mistakes (missing file,
    unknown format, no overlap) raise DatasetError/EvalError with one line.
    """
    est_path, gt_path = Path(est_path), Path(gt_path)
    est_fmt = _resolve_format(est_path, est_format)
    gt_fmt = _resolve_format(gt_path, gt_format)
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
