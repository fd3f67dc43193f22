"""``Pipeline``: open a sequence, track every frame, write the trajectory as it is produced, then evaluate
against ground truth.

``tracker`` picks the front end: the frame-to-frame baseline odometry (``vslam.tracking.baseline``) or the SLAM
core (``vslam.tracking.slam``: map, local BA), both behind the ``Odometry`` protocol
(``track(frame) -> FrameEstimate``, ``finish(out_dir) -> paths``, final poses and maps).
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from vslam.config import to_dict
from vslam.data.live import LiveSequence
from vslam.data.registry import open_dataset
from vslam.data.select import select_frames
from vslam.data.trajectory import Trajectory, TrajectoryWriter, write_trajectory
from vslam.data.types import Sequence
from vslam.errors import TrackingError, VslamError
from vslam.eval import evaluate, write_report
from vslam.geometry.se3 import interpolate_poses
from vslam.outputs import OUTPUT_ERRNOS, OutputError, describe_failure, prepare_run_dir, write_text
from vslam.pipeline.config import PipelineConfig
from vslam.pipeline.frames import frontend_process, prefetch, skipped_frames
from vslam.pipeline.result import RunResult
from vslam.pipeline.runtime import blas_threads, torch_threads
from vslam.tracking.baseline import FrameEstimate, FrameToFrameOdometry, Odometry
from vslam.tracking.slam import SlamTracker

log = logging.getLogger(__name__)


# status / uncertain / pose_std_*: see FrameEstimate (faulty frames are kept and marked uncertain;
# a frame whose timestamp does not increase gets status "duplicate_time" and no trajectory line). map_id: the
# map the frame's pose is in (a new map when tracking is lost; see ``vslam.tracking.atlas``).
# ms_map_*: the local-mapping sub-stages, blank on frames that made no keyframe. n_lines / n_line_inliers:
# segments detected / map lines kept by the pose refinement, blank without line features.
# imu: "used" / "off" (visual-only: no usable IMU samples over this stretch, an IMU factor dropped as
# inconsistent with vision, or until the keyframe that restarts the IMU chain), blank without an IMU.
# ms_detector: the dynamic-object detector (slam.dynamic.source=detector), blank otherwise.
# dropped: frames the live queue dropped since the previous row (``vslam.data.live``); 0 for recorded input.
# map_id: the map the frame was tracked in; final_map_id: the map it ended in after merges (filled at the end)
STAT_COLUMNS = ("index", "timestamp", "dropped", "map_id", "final_map_id", "tracked", "status", "uncertain", "pose_std_m", "pose_std_deg", "n_features",
                "n_matches", "n_inliers", "n_lines", "n_line_inliers", "imu", "ms_decode", "ms_features", "ms_detector",
                "ms_dynamic", "ms_lines", "ms_depth", "ms_pose", "ms_mapping", "ms_map_create", "ms_map_fuse_cull",
                "ms_map_ba", "ms_map_wait", "ms_map_loop", "ms_map_merge", "ms_total")


def _write_final_maps(path: Path, stats: list[dict], odo: Odometry) -> None:
    """stats.csv again, its final_map_id column filled (the map each frame ended in after the merges); written
    whole to a temporary file and renamed, so the per-frame file written during the run is never half-replaced."""
    from vslam.outputs import atomic_open

    ids = [int(r["map_id"]) for r in stats if "map_id" in r]
    final = iter(odo.final_map_ids(ids))
    for r in stats:
        if "map_id" in r:
            r["final_map_id"] = int(next(final))
    with atomic_open(path, "w", newline="") as f:
        sw = csv.writer(f)
        sw.writerow(STAT_COLUMNS)
        for r in stats:
            sw.writerow(_stat_cells(r))


def _stat_cells(row: dict) -> list[str]:
    """One stats.csv line: the row's values in STAT_COLUMNS order, blank where it has none."""
    return [_fmt_stat(c, row.get(c, "")) for c in STAT_COLUMNS]


def _fmt_stat(col: str, v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if col.startswith("pose_std"):
            return "nan" if not np.isfinite(v) else f"{v:.6g}"
        return f"{v:.6f}" if col == "timestamp" else f"{v:.3f}"
    return str(v)


class Pipeline:
    """``Pipeline(config).run(sequence)``: the Python API behind ``vslam run``."""

    def __init__(self, config: PipelineConfig = PipelineConfig()):
        self.config = config

    def _evaluate(self, seq: Sequence, traj: Trajectory, result: RunResult, out: Path) -> None:
        """ATE/RPE against the ground truth. With several maps (never merged) each is aligned and scored on its
        own (``RunResult.map_evals``, ``report/maps.json``); the report's headline is the map with most frames."""
        cfg = self.config
        gt = seq.groundtruth()
        if gt is None:
            return
        if len(traj) < 3:
            result.eval_skipped = f"ground truth found, but {len(traj)} pose(s) are too few to align (at least 3)"
            return
        result.paths["groundtruth"] = write_trajectory(out / "groundtruth.tum.txt", gt, "tum")
        result.eval_groundtruth = gt
        # auto alignment: Sim3 where the scale is not observed (monocular without an IMU-scaled map), else SE3
        unscaled = not result.metric_scale
        ids = result.map_ids if result.map_ids is not None else np.zeros(len(traj), np.int64)
        maps, counts = np.unique(ids, return_counts=True)
        if len(maps) > 1:
            for m, n in zip(maps.tolist(), counts.tolist()):
                if n >= 3:
                    try:
                        result.map_evals[m] = evaluate(traj.subset(np.flatnonzero(ids == m)), gt, cfg.eval,
                                                       monocular=unscaled)
                    except VslamError as e:  # a map too short to align: said, not fatal
                        log.warning("map %d (%d frames) not evaluated: %s", m, n, e)
            main = int(maps[np.argmax(counts)])
            result.scored_map = main
            traj = traj.subset(np.flatnonzero(ids == main))
        result.eval = evaluate(traj, gt, cfg.eval, monocular=unscaled)
        if cfg.output.report:
            result.paths.update(write_report(result.eval, out / "report", title=f"vslam run: {seq.name}",
                                             run=result.run_summary(), maps=result.map_evals))
            if result.map_evals:
                result.paths["report_maps"] = write_text(out / "report" / "maps.json", json.dumps(
                    {str(m): {"frames": int(np.sum(ids == m)), **e.to_dict()} for m, e in result.map_evals.items()},
                    indent=1))

    def run(
        self,
        sequence: Sequence | None = None,
        out_dir: str | Path | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> RunResult:
        cfg = self.config
        # a sequence the run opens it also closes (video capture, bag reader, camera); one the caller passes in
        # stays open: the caller owns it (``with seq:`` or ``seq.close()``)
        opened = open_dataset(cfg.dataset) if sequence is None else None
        try:
            seq = select_frames(opened if opened is not None else sequence,  # type: ignore[arg-type]
                                cfg.dataset.stride, cfg.dataset.drop, cfg.dataset.jpeg_quality)
            out = Path(out_dir or cfg.output.dir)
            prepare_run_dir(out, keep=(cfg.slam.load_map,))
            try:
                with getattr(seq, "stop_on_interrupt", contextlib.nullcontext)():  # live: Ctrl-C ends the stream
                    return self._run(seq, out, progress)
            except OSError as e:  # an output that cannot be written: which one, and what the folder holds
                if e.errno not in OUTPUT_ERRNOS:
                    raise
                raise OutputError(describe_failure(out, e)) from None
        finally:
            if opened is not None:
                opened.close()

    def _run(self, seq: Sequence, out: Path, progress: Callable[[int, int], None] | None) -> RunResult:
        cfg = self.config
        paths: dict[str, Path] = {"config": write_text(out / "config.yaml", yaml.safe_dump(to_dict(cfg), sort_keys=False))}
        writers = {f: TrajectoryWriter(out / f"trajectory.{f}.txt", f) for f in cfg.output.formats}
        paths.update({f"trajectory_{f}": w.path for f, w in writers.items()})
        live = isinstance(seq, LiveSequence)  # no length: frames until the stream ends; its queue drops
        n_total = (cfg.dataset.max_frames or sys.maxsize) if live else \
            len(seq) if cfg.dataset.max_frames <= 0 else min(len(seq), cfg.dataset.max_frames)
        n_dropped, last_index = 0, -1
        ahead = cfg.tracker == "slam" and cfg.runtime.frontend_thread
        # started first: the child's imports overlap building the tracker here
        # (not for live input: the camera is this process's; its front end runs on the prefetch thread)
        child = frontend_process(seq, n_total, cfg) if ahead and cfg.runtime.frontend_process and not live else None
        odo: Odometry
        try:
            if cfg.tracker == "slam":
                odo = SlamTracker(seq.calibration, cfg.dataset.sensor, cfg.slam, runtime=cfg.runtime)
            else:
                odo = FrameToFrameOdometry(seq.calibration, cfg.dataset.sensor, cfg.odometry)
        except BaseException:
            if child is not None:
                child.close()
            raise
        stamps: list[float] = []
        indices: list[int] = []
        backfill: dict[int, np.ndarray] = {}  # frame index -> pose measured late (FrameEstimate.backfill)
        poses: list[np.ndarray] = []
        tracked: list[bool] = []
        map_ids: list[int] = []  # the map each written pose is in (``vslam.tracking.atlas``)
        unposed: list[tuple[float, int]] = []  # (time, index) of frames with no pose: before a map, between maps
        backfill_map: dict[int, int] = {}
        stats: list[dict[str, float]] = []
        stats_path = out / "stats.csv"
        paths["stats"] = stats_path
        t_start = time.perf_counter()
        viewer = None
        try:
            if cfg.output.viewer.enabled:  # rerun is imported only then
                from vslam.viz.rerun_log import RerunLogger

                viewer = RerunLogger(cfg.output.viewer, seq, odo, cfg.eval.enabled, cfg.dataset.max_diff)
            runtime = cfg.runtime if cfg.tracker == "slam" else None
            with torch_threads(runtime), blas_threads(runtime), open(stats_path, "w", newline="") as fstats:
                sw = csv.writer(fstats)
                sw.writerow(STAT_COLUMNS)
                frames = iter(child) if child is not None else prefetch(seq, n_total, 1 if live else 3,
                                                                         prepare=odo.frontend if ahead else None)
                k = -1
                while True:
                    t_wait = time.perf_counter()
                    item = next(frames, None)  # made ahead, beside tracking: this is the time tracking waited
                    if item is None:  # the generator is exhausted (and has joined its thread)
                        break
                    frame, front = item
                    k += 1
                    ms_decode = (time.perf_counter() - t_wait) * 1e3
                    dropped = frame.index - last_index - 1 if live else 0  # live frames are numbered in grab order
                    n_dropped, last_index = n_dropped + dropped, frame.index
                    if stamps and not frame.timestamp > stamps[-1]:
                        # A second image at the same instant would give a trajectory no reader accepts
                        # (time must increase); it is not tracked, only recorded in stats.csv.
                        log.warning("frame %d: timestamp %.6f does not increase (previous %.6f); frame skipped",
                                    frame.index, frame.timestamp, stamps[-1])
                        row = {"index": frame.index, "timestamp": frame.timestamp, "dropped": dropped, "tracked": 0,
                               "status": "duplicate_time", "uncertain": 1, "pose_std_m": float("nan"),
                               "pose_std_deg": float("nan")}
                        sw.writerow(_stat_cells(row))
                        fstats.flush()
                        stats.append(row)
                        continue
                    t0 = time.perf_counter()
                    est: FrameEstimate = odo.track(frame, front) if front is not None else odo.track(frame)
                    ms = (time.perf_counter() - t0) * 1e3
                    if est.has_pose:  # a frame between two maps has none: listed in stats.csv only
                        for w in writers.values():
                            w.write(frame.timestamp, est.T_world_cam)
                    std_m, std_deg = est.pose_std()
                    row = {"index": frame.index, "timestamp": frame.timestamp, "dropped": dropped, "map_id": est.map_id,
                           "tracked": int(est.tracked),
                           "status": est.status_name, "uncertain": int(est.uncertain), "pose_std_m": std_m,
                           "pose_std_deg": std_deg,
                           "n_features": est.n_features, "n_matches": est.n_matches, "n_inliers": est.n_inliers,
                           "n_lines": est.n_lines, "n_line_inliers": est.n_line_inliers, "imu": est.imu,
                           "ms_decode": ms_decode, **{f"ms_{k2}": v for k2, v in est.times_ms.items()}, "ms_total": ms}
                    sw.writerow(_stat_cells(row))
                    fstats.flush()
                    stats.append(row)
                    if viewer is not None:
                        viewer.log_frame(frame, est, row)
                    backfill.update(est.backfill)
                    backfill_map.update({i: est.map_id for i in est.backfill})
                    if not est.has_pose:
                        unposed.append((frame.timestamp, frame.index))
                    else:
                        stamps.append(frame.timestamp)
                        indices.append(frame.index)
                        poses.append(est.T_world_cam)
                        tracked.append(est.tracked)
                        map_ids.append(est.map_id)
                    if progress:
                        progress(k + 1, n_total if n_total < sys.maxsize else 0)  # 0: total unknown
        finally:
            for w in writers.values():
                w.close()
            if child is not None:
                child.close()
            if viewer is not None:
                viewer.close()
        seconds = time.perf_counter() - t_start
        paths.update(odo.finish(out))  # keyframes and map (SLAM); nothing for the baseline
        # monocular frames seen before the map existed (no pose then): localised once it did, they join the
        # final trajectory in time order
        late = [(t, i) for t, i in unposed if i in backfill]
        if late:
            stamps += [t for t, _ in late]
            indices += [i for _, i in late]
            poses += [backfill[i] for _, i in late]
            tracked += [True] * len(late)
            map_ids += [backfill_map[i] for _, i in late]
            order = np.argsort(np.array(stamps), kind="stable")
            stamps, indices, poses, tracked, map_ids = ([x[j] for j in order] for x in (stamps, indices, poses,
                                                                                         tracked, map_ids))
            log.info("%d frames before the monocular initialisation localised afterwards", len(late))
        # a loop closure, a merge or a monocular inertial rescale moved the keyframes: every frame follows its own
        final = odo.final_poses(indices) if len(poses) else None
        if final is not None:
            poses = list(final)
        final_ids = np.array(odo.final_map_ids(map_ids), np.int64)
        # frames predicted through a failure: in the final trajectory, between the measured frames around them
        # (same map) rather than extrapolated from the ones before; trajectory.tum.txt keeps the prediction
        smoothed, filled = interpolate_poses(np.array(stamps), np.array(poses).reshape(-1, 4, 4),
                                             np.array(tracked, bool), final_ids)
        if filled.any():
            poses = list(smoothed)
            log.info("%d predicted frames interpolated between measured ones in trajectory_final.tum.txt",
                     int(filled.sum()))
        if final is not None or late or filled.any():
            paths["trajectory_final"] = write_trajectory(out / "trajectory_final.tum.txt",
                                                         Trajectory(np.array(stamps), np.array(poses)), "tum")
        # maps never merged into one another: each frame's pose is in its own map's frame
        maps, counts = np.unique(final_ids, return_counts=True)
        main_map = int(maps[np.argmax(counts)]) if len(maps) else 0
        if len(maps) > 1:
            log.warning("%d maps were never merged (frames per map: %s); trajectory_final.tum.txt holds %s",
                        len(maps), dict(zip(maps.tolist(), counts.tolist())),
                        "every map, each in its own frame (stats.csv map_id)" if cfg.output.unmerged == "keep"
                        else f"map {main_map} only (output.unmerged: drop)")
            keep = np.ones(len(poses), bool) if cfg.output.unmerged == "keep" else final_ids == main_map
            paths["trajectory_final"] = write_trajectory(
                out / "trajectory_final.tum.txt",
                Trajectory(np.array(stamps)[keep], np.array(poses).reshape(-1, 4, 4)[keep]), "tum")
        _write_final_maps(stats_path, stats, odo)
        traj = Trajectory(np.array(stamps), np.array(poses).reshape(-1, 4, 4))
        result = RunResult(traj, np.array(tracked, bool), stats, None, paths, seconds)
        result.map_ids = final_ids
        result.recovery = odo.recovery_stats()
        result.dropped = n_dropped if live else None
        result.metric_scale = bool(odo.metric_scale)
        if not live:
            result.skipped = skipped_frames(seq, [int(r["index"]) for r in stats], n_total)
        result.association = getattr(seq, "association", None)
        if not stats:  # nothing reached the tracker: every frame failed to decode, or the selection kept none
            why = f"; {len(result.skipped)} did not decode" if result.skipped else ""
            result.error = TrackingError(f"no frame of {seq.name} was read{why}: nothing to track")
            result.eval_skipped = "no frame was read"
        elif not any(tracked):
            # no map was ever made (or only predicted poses): not a result, whatever was written
            result.error = TrackingError(
                f"no frame of {len(stats)} was tracked: {paths.get('trajectory_tum', out)} holds no measured pose "
                f"(status per frame in {stats_path}); check the sensor, the calibration and slam.features")
        elif cfg.eval.enabled:
            try:
                self._evaluate(seq, traj, result, out)
            except VslamError as e:  # the trajectory is written: report the ground truth's problem after it
                result.error = e
                result.eval_skipped = str(e).splitlines()[0] if str(e) else type(e).__name__
        log.info("%d frames in %.1f s (%.1f frames/s), %d tracked%s", len(traj), seconds, result.fps, int(np.sum(tracked)),
                 f", {n_dropped} dropped by the live queue" if live else "")
        return result
