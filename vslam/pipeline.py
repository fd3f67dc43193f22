"""Wires the stages from one config: open a sequence, track every frame,
write the trajectory as it is produced, then evaluate against ground truth.

``tracker`` picks the front end: the frame-to-frame baseline odometry
(`vslam.tracking.baseline`) or the SLAM core (`vslam.tracking.slam`: map,
local BA), both behind the same ``track(frame) -> FrameEstimate`` and
``finish(out_dir) -> paths`` calls.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import logging
import pickle
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Literal

import numpy as np
import yaml

from vslam.childproc import usable_cpus
from vslam.config import from_dict, load_config, to_dict
from vslam.data.bag import BagTopics
from vslam.data.live import LiveConfig, LiveSequence
from vslam.data.select import kept_indices, select_frames
from vslam.data.trajectory import Trajectory, TrajectoryWriter, write_trajectory
from vslam.data.types import Frame, Sequence
from vslam.errors import ConfigError, DatasetError, TrackingError, VslamError
from vslam.geometry.se3 import interpolate_poses
from vslam.eval import EvalConfig, EvalResult, evaluate, write_report
from vslam.outputs import OUTPUT_ERRNOS, OutputError, describe_failure, prepare_run_dir, write_text
from vslam.paths import data_root
from vslam.tracking.baseline import FrameEstimate, FrameToFrameOdometry, OdometryConfig
from vslam.tracking.slam import SlamConfig, SlamTracker
from vslam.viz.rerun_log import ViewerConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DatasetConfig:
    """Which sequence to run. ``path`` relative to the data root ($VSLAM_DATA or ../shared/data) unless absolute."""

    kind: Literal["auto", "tum", "kitti", "euroc", "synthetic", "images", "video", "bag", "live"] = "synthetic"
    path: str = ""
    sensor: Literal["rgbd", "stereo", "mono"] = "rgbd"
    max_diff: float = 0.02  # seconds, image/depth/ground-truth association
    max_frames: int = 0  # 0 = all frames
    # every stride-th frame, and frame-index ranges [first, last] cut out (a low frame rate, a camera that
    # drops out: ``vslam.data.select``); max_frames counts the frames left
    stride: int = 1
    drop: tuple[tuple[int, int], ...] = ()
    synthetic: dict[str, Any] = field(default_factory=dict)  # SyntheticConfig fields when kind == synthetic
    # your own data (kinds images, video, bag; docs/inputs.md): camera file ("" = camera.yaml beside the data),
    # frame times from a times file or a rate (0 = from the file names / the container / the bag's stamps)
    camera: str = ""
    times: str = ""
    fps: float = 0.0
    topics: BagTopics = BagTopics()
    # kind live: path is a camera index, stream URL, realsense[:SERIAL] or a video file (vslam.data.live)
    live: LiveConfig = LiveConfig()

    def __post_init__(self) -> None:
        kept_indices(0, self.stride, self.drop)  # the same checks as when they are applied


@dataclass(frozen=True)
class OutputConfig:
    dir: str = "runs/latest"
    formats: tuple[str, ...] = ("tum", "kitti")
    report: bool = True
    # maps that were never merged into the one with most frames: kept in trajectory_final.tum.txt (each in its
    # own frame; stats.csv says which) or dropped from it
    unmerged: Literal["keep", "drop"] = "keep"
    viewer: ViewerConfig = ViewerConfig()  # stream the run to Rerun (vslam.viz.rerun_log, docs/viewer.md); off


@dataclass(frozen=True)
class PipelineConfig:
    dataset: DatasetConfig = DatasetConfig()
    tracker: Literal["baseline", "slam"] = "slam"  # baseline: frame-to-frame odometry; slam: map + local BA
    odometry: OdometryConfig = OdometryConfig()  # settings of the baseline tracker
    slam: SlamConfig = SlamConfig()  # settings of the SLAM tracker
    eval: EvalConfig = EvalConfig()
    output: OutputConfig = OutputConfig()

    @staticmethod
    def load(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> PipelineConfig:
        return load_config(PipelineConfig, path, overrides, nonnegative=True)


@dataclass
class RunResult:
    trajectory: Trajectory
    tracked: np.ndarray  # (N,) bool: measured (True) or predicted through a failure (False)
    stats: list[dict[str, float]]
    eval: EvalResult | None
    paths: dict[str, Path]
    seconds: float
    # A problem found once the trajectory was written (ground truth unusable, no frame tracked): the run's
    # outputs stand, and ``vslam run`` reports it as an error after them.
    error: VslamError | None = None
    # the final map of each written pose, and the evaluation of each map when there are several
    map_ids: np.ndarray | None = None
    map_evals: dict[int, EvalResult] = field(default_factory=dict)
    eval_groundtruth: Trajectory | None = None  # what ``eval`` was measured against
    dropped: int | None = None  # live input: frames its queue dropped (stats.csv ``dropped``); None: recorded input
    # the trajectory is in metres (depth, stereo, an IMU-scaled monocular map); False: scored with Sim3
    metric_scale: bool = True
    # the map ``eval`` scores when maps were never merged (the one with most poses); None: the whole run
    scored_map: int | None = None
    # why ground truth was found but not used (too few poses to align), for the summary
    eval_skipped: str = ""
    # indices of the frames the reader could not decode (skipped with a warning; no stats.csv row)
    skipped: list[int] = field(default_factory=list)
    # how the reader paired rgb with depth / left with right over the recording (None: nothing to pair)
    association: Any = None

    @property
    def fps(self) -> float:
        return len(self.trajectory) / self.seconds if self.seconds > 0 else float("nan")

    @property
    def n_frames(self) -> int:
        """Frames the run read (a row each in stats.csv), posed or not."""
        return len(self.stats)

    def maps_summary(self) -> list[dict[str, Any]]:
        """One entry per final map, largest first: id, poses, and its own ATE when it was scored."""
        ids = self.map_ids if self.map_ids is not None else np.zeros(len(self.trajectory), np.int64)
        maps, counts = np.unique(ids, return_counts=True)
        out = []
        for m, n in sorted(zip(maps.tolist(), counts.tolist()), key=lambda mn: (-mn[1], mn[0])):
            e = self.map_evals.get(m) if self.map_evals else (self.eval if len(maps) == 1 else None)
            entry: dict[str, Any] = {"map": int(m), "poses": int(n), "tracked": int(np.sum(self.tracked[ids == m]))}
            if e is not None:
                entry.update(ate_rmse=e.ate.translation.rmse, align=e.alignment.method, scale=e.alignment.s,
                             matched=e.n_matched)
            out.append(entry)
        return out

    def run_summary(self) -> dict[str, Any]:
        """The whole run in numbers (``metrics.json`` ``run``): frames read, posed, tracked, the maps, and what
        the headline ATE scores."""
        n, posed = self.n_frames, len(self.trajectory)
        return {"frames": n, "skipped": len(self.skipped), "posed": posed, "posed_fraction": posed / n if n else 0.0,
                "tracked": int(self.tracked.sum()), "metric_scale": self.metric_scale,
                "scored": "whole run" if self.scored_map is None else f"largest map ({self.scored_map})",
                "scored_map": self.scored_map, "maps": self.maps_summary(),
                "association": dataclasses.asdict(self.association) if self.association is not None else None}


def open_dataset(cfg: DatasetConfig) -> Sequence:
    """The Sequence a DatasetConfig names (synthetic ones are generated lazily in memory)."""
    if cfg.kind == "synthetic":
        from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

        scfg = from_dict(SyntheticConfig, dict(cfg.synthetic), "dataset.synthetic", prefix="dataset.synthetic.")
        return SyntheticSequence(scfg, sensor=cfg.sensor)
    from vslam.data.registry import detect_kind, open_sequence

    if cfg.kind == "live":  # frames as they come: nothing to select from, a queue that drops instead
        if cfg.stride != 1 or cfg.drop:
            raise ConfigError("dataset.stride and dataset.drop select frames of a recording; a live source has "
                              "none to select (its queue drops the frames the tracker cannot take)")
        return open_sequence(cfg.path, kind="live", camera=_data_path(cfg.camera), sensor=cfg.sensor,
                             config=cfg.live)
    if not cfg.path:
        raise ConfigError("dataset.path is empty; give the sequence folder (or use kind: synthetic)")
    path = Path(cfg.path).expanduser()
    if not path.is_absolute() and not path.exists():
        path = data_root() / path
    layout = _layout(path)
    kind = layout if cfg.kind == "auto" else cfg.kind
    if layout is not None and kind != layout:
        raise ConfigError(f"dataset.kind is {kind!r} but {path} has the {layout} layout; use a config for "
                          f"{layout} (or --kind {layout} with --sensor)")
    if kind is None and cfg.camera and path.is_dir():  # a plain image folder, its camera file given apart
        kind = "images"
    if kind is None:
        kind = detect_kind(path)  # raises, naming what it looked for
    options: dict[str, Any] = {"sensor": cfg.sensor}
    if kind in ("tum", "euroc", "images", "bag"):  # KITTI frames are matched by index, not time
        options["max_diff"] = cfg.max_diff
    if kind in ("images", "video", "bag"):
        options.update(camera=_data_path(cfg.camera), **({"topics": cfg.topics} if kind == "bag" else
                                                          {"times": _data_path(cfg.times), "fps": cfg.fps}))
    return open_sequence(path, kind=kind, **options)


def _data_path(p: str) -> Path | None:
    """A user-given file path (camera, times) as given, None when empty."""
    return Path(p).expanduser() if p else None


def _layout(path: Path) -> str | None:
    """The dataset kind ``path``'s layout shows, None when it shows none."""
    from vslam.data.registry import detect_kind

    try:
        return detect_kind(path)
    except DatasetError:
        return None


def prefetch(seq: Sequence, n: int, depth: int = 3,
             prepare: Callable[[Frame], Any] | None = None) -> Iterator[tuple[Frame, Any]]:
    """The first ``n`` frames of ``seq`` as (frame, prepare(frame) or None), made on a background thread while
    the caller tracks.

    PNG decoding and ``prepare`` (the tracker's image-only front end: OpenCV and torch release the GIL) then
    overlap tracking on a second core; the order and content of the frames are unchanged, and an exception
    in the reader or in ``prepare`` is re-raised here.
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def produce() -> None:
        try:
            for k, frame in enumerate(seq):
                if k >= n or stop.is_set():
                    break
                q.put((frame, prepare(frame) if prepare is not None else None))
            q.put(done)
        except BaseException as e:  # handed to the consumer, raised in its thread
            q.put(e)

    worker = threading.Thread(target=produce, name="vslam-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        while worker.is_alive():  # unblock a producer waiting on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                worker.join(0.01)


# status / uncertain / pose_std_*: see FrameEstimate (issue 3: faulty frames are kept and marked uncertain;
# a frame whose timestamp does not increase gets status "duplicate_time" and no trajectory line). map_id: the
# map the frame's pose is in (issue 38: a new map when tracking is lost; see ``vslam.tracking.atlas``).
# ms_map_*: the local-mapping sub-stages, blank on frames that made no keyframe. n_lines / n_line_inliers:
# segments detected / map lines kept by the pose refinement, blank without line features.
# imu: "used" / "off" (visual-only: no usable IMU samples over this stretch, an IMU factor dropped as
# inconsistent with vision, or until the keyframe that restarts the IMU chain), blank without an IMU.
# ms_detector: the dynamic-object detector (slam.dynamic.source=detector), blank otherwise.
# dropped: frames the live queue dropped since the previous row (``vslam.data.live``); 0 for recorded input.
STAT_COLUMNS = ("index", "timestamp", "dropped", "map_id", "tracked", "status", "uncertain", "pose_std_m", "pose_std_deg", "n_features",
                "n_matches", "n_inliers", "n_lines", "n_line_inliers", "imu", "ms_decode", "ms_features", "ms_detector",
                "ms_dynamic", "ms_lines", "ms_depth", "ms_pose", "ms_mapping", "ms_map_create", "ms_map_fuse_cull",
                "ms_map_ba", "ms_map_wait", "ms_map_loop", "ms_total")


def _fmt_stat(col: str, v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        if col.startswith("pose_std"):
            return "nan" if not np.isfinite(v) else f"{v:.6g}"
        return f"{v:.6f}" if col == "timestamp" else f"{v:.3f}"
    return str(v)


@contextlib.contextmanager
def blas_threads(cfg: SlamConfig | None) -> Iterator[None]:
    """numpy's BLAS thread count for a run (``SlamConfig.blas_threads``), restored afterwards."""
    if cfg is None or cfg.blas_threads <= 0:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=cfg.blas_threads, user_api="blas"):
        yield


def torch_thread_count(cfg: SlamConfig) -> int:
    """``SlamConfig.torch_threads``, or 0 resolved: the CPUs, less one for the tracking thread when the front end
    runs beside it (on a thread or in the child process, which uses the same count)."""
    return cfg.torch_threads or max(1, usable_cpus() - (1 if cfg.frontend_thread else 0))


@contextlib.contextmanager
def torch_threads(cfg: SlamConfig | None) -> Iterator[None]:
    """torch's intra-op thread count for a run (``SlamConfig.torch_threads``), restored afterwards; nothing when
    the run loaded no network (torch not imported)."""
    torch = sys.modules.get("torch")
    if cfg is None or torch is None:
        yield
        return
    n = torch_thread_count(cfg)
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _frontend_process(seq: Sequence, n: int, cfg: PipelineConfig):
    """A ``FrontEndProcess`` for the run (``SlamConfig.frontend_process``), or None -- the prefetch thread
    then -- when the sequence cannot be sent to a child process or no child can be started."""
    from vslam.tracking.frontend_process import FrontEndProcess

    try:
        return FrontEndProcess(seq, n, seq.calibration, cfg.dataset.sensor, cfg.slam,
                               torch_threads=torch_thread_count(cfg.slam),
                               blas_threads=cfg.slam.blas_threads)
    except (TypeError, AttributeError, pickle.PicklingError, OSError) as e:
        log.info("front end on a thread: the sequence cannot be sent to a child process, or none started (%s)", e)
        return None


def _skipped_frames(seq: Sequence, received: list[int], n_total: int) -> list[int]:
    """Indices of the frames the run should have read but the reader skipped (they did not decode): the holes in
    the indices received, and the missing tail when the reading stopped early. Taken from the indices, not from
    the reader's ``skipped`` list: a front-end process reads (and skips) in a child, whose list is not ours, and a
    video lists its lost frames for the whole file, also past where the run stopped."""
    expected = np.asarray(getattr(seq, "indices", np.arange(len(seq))), np.int64)
    got = set(received)
    last = max(received) if received else -1
    holes = {int(i) for i in expected[expected <= last] if int(i) not in got}
    missing = n_total - len(received) - len(holes)
    if missing > 0:  # the reading stopped before the frames it was asked for: the rest did not decode
        holes |= set(expected[expected > last][:missing].tolist())
    return sorted(holes)


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
                                cfg.dataset.stride, cfg.dataset.drop)
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
        ahead = cfg.tracker == "slam" and cfg.slam.frontend_thread
        # started first: the child's imports overlap building the tracker here
        # (not for live input: the camera is this process's; its front end runs on the prefetch thread)
        child = _frontend_process(seq, n_total, cfg) if ahead and cfg.slam.frontend_process and not live else None
        odo: FrameToFrameOdometry | SlamTracker
        try:
            if cfg.tracker == "slam":
                odo = SlamTracker(seq.calibration, cfg.dataset.sensor, cfg.slam)
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
            slam_cfg = cfg.slam if cfg.tracker == "slam" else None
            with torch_threads(slam_cfg), blas_threads(slam_cfg), open(stats_path, "w", newline="") as fstats:
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
                        sw.writerow([_fmt_stat(c, row.get(c, "")) for c in STAT_COLUMNS])
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
                    sw.writerow([_fmt_stat(c, row.get(c, "")) for c in STAT_COLUMNS])
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
        final = odo.final_poses(indices) if hasattr(odo, "final_poses") and len(poses) else None
        if final is not None:
            poses = list(final)
        final_ids = np.array(odo.final_map_ids(map_ids) if hasattr(odo, "final_map_ids") else map_ids, np.int64)
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
        traj = Trajectory(np.array(stamps), np.array(poses).reshape(-1, 4, 4))
        result = RunResult(traj, np.array(tracked, bool), stats, None, paths, seconds)
        result.map_ids = final_ids
        result.dropped = n_dropped if live else None
        result.metric_scale = bool(odo.metric_scale)
        if not live:
            result.skipped = _skipped_frames(seq, [int(r["index"]) for r in stats], n_total)
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
