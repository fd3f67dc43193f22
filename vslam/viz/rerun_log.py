"""A run as a Rerun recording (watch it live, docs/viewer.md): ``RerunLogger.log_frame`` once per frame.

Entity tree (docs/viewer.md), world = the map's frame (the first camera, OpenCV axes: x right, y down, z ahead):

    world/camera                      Transform3D  T_world_cam of the frame (frames with a pose)
    world/camera/image                Pinhole (static) + the image (JPEG unless ``jpeg_quality`` = 0)
    world/camera/image/keypoints/{tracked,dynamic,new}   Points2D, raw pixels: matched to a map point /
                                      dropped as on a moving object (mask, detector, motion check) / neither
    world/camera/image/boxes/{detector,dataset}          Boxes2D: the detector's, the sequence's own
    world/camera/image/dynamic_mask   SegmentationImage: the sequence's mask of moving objects (synthetic)
    world/camera/image/lines          LineStrips2D: line segments (``slam.lines``)
    world/trajectory/{estimated,recent}   LineStrips3D: camera centres so far (one strip per map)
    world/trajectory/groundtruth      LineStrips3D (static): anchored at the first estimated pose
    world/map/{points,keyframes}      Points3D of the current map, every ``map_every`` frames and at the end
    world/map/{loops,merges}          LineStrips3D: keyframe pairs of loop closures / map merges
    stats/ms/<stage>, stats/count/<n>, stats/pose_std/{m,deg}   Scalars: the frame's stats.csv row
    status, events                    TextLog: the frame's status; loops, merges, new maps

Timelines: ``frame`` (frame index) and ``time`` (the frame's timestamp, seconds). ``rerun`` is imported when a
logger is made, never by importing this module: with the viewer off a run costs nothing.
"""

from __future__ import annotations

import logging
import os
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vslam.data.types import Frame, Sequence
from vslam.errors import ConfigError

log = logging.getLogger(__name__)

TRACKED, DYNAMIC, NEW = 0, 1, 2  # keypoint fates (``keypoint_fates``)
FATE_NAMES = ("tracked", "dynamic", "new")
FATE_COLORS = ((40, 220, 60), (235, 40, 40), (250, 200, 30))  # RGB
COUNT_COLUMNS = ("n_features", "n_matches", "n_inliers", "n_lines", "n_line_inliers")


@dataclass(frozen=True)
class ViewerConfig:
    """Where a run is streamed (any of the three; none = off, the default) and how much is logged."""

    spawn: bool = False  # start the Rerun viewer and stream to it (``vslam run --viewer``)
    rrd: str = ""  # record to this .rrd file (``--rrd FILE``; open it later with ``rerun FILE``)
    serve: bool = False  # serve the web viewer on web_port, the data over gRPC on grpc_port (``--serve``)
    grpc_port: int = 9876
    web_port: int = 9090
    # the image as JPEG at this quality; 0 = raw pixels (exact, but ~0.9 MB per VGA colour frame in the .rrd)
    jpeg_quality: int = 75
    # frames between refreshes of the map points, keyframes and the full trajectory (each is O(map) to log;
    # the trajectory's last stretch is logged every frame as world/trajectory/recent)
    map_every: int = 10

    @property
    def enabled(self) -> bool:
        return self.spawn or self.serve or bool(self.rrd)

    def __post_init__(self) -> None:
        if not 0 <= self.jpeg_quality <= 100:
            raise ConfigError(f"output.viewer.jpeg_quality must be in 0..100 (0: raw pixels), got {self.jpeg_quality}")
        if self.map_every < 1:
            raise ConfigError(f"output.viewer.map_every must be at least 1, got {self.map_every}")


def web_viewer_url(cfg: ViewerConfig) -> str:
    """The address ``serve`` opens in a browser."""
    return f"http://localhost:{cfg.web_port}/?url=rerun%2Bhttp://localhost:{cfg.grpc_port}/proxy"


def keypoint_fates(view: Any) -> np.ndarray:
    """(N,) int8 fate of each keypoint of ``view.front.feats`` (a ``vslam.tracking.slam.FrameView``): TRACKED
    (matched to a map point), DYNAMIC (dropped by dynamic filtering or flagged moving), NEW (neither)."""
    n = len(view.front.feats)
    if view.kept is None:
        kept = np.arange(n)
        fate = np.full(n, NEW, np.int8)
    else:
        kept = np.asarray(view.kept, np.int64)
        fate = np.full(n, DYNAMIC, np.int8)
        fate[kept] = NEW
    if view.point_ids is not None:
        fate[kept[np.asarray(view.point_ids) >= 0]] = TRACKED
    if view.moving is not None:
        fate[kept[np.asarray(view.moving, bool)]] = DYNAMIC
    return fate


def _strips(pos: np.ndarray, ids: np.ndarray) -> list[np.ndarray]:
    """(N,3) positions split where the map id (N,) changes: one line strip per stretch of one map."""
    if not len(pos):
        return []
    cuts = np.flatnonzero(np.diff(ids)) + 1
    return [s for s in np.split(pos, cuts) if len(s)]


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError:
        raise ConfigError("the viewer (--viewer, --rrd, --serve; output.viewer) needs rerun-sdk: "
                          "pip install 'vslam[viewer]'") from None
    return rr


class RerunLogger:
    """Streams a run to Rerun. ``log_frame(frame, est, row)`` after each tracked frame, ``close()`` at the end.

    ``tracker``: the run's tracker; read, never changed: ``view`` (the frame's keypoints and their fate), ``map``
    (points, keyframes), ``loop.stats.loops`` and ``atlas.merges`` where it has them (the SLAM tracker).
    ``groundtruth``: log the sequence's ground truth (read once, at the first pose; not for monocular runs,
    whose scale is the map's own).
    """

    def __init__(self, cfg: ViewerConfig, seq: Sequence, tracker: Any, groundtruth: bool = True,
                 max_diff: float = 0.02):
        self.rr = rr = _import_rerun()
        self.cfg, self.seq, self.tracker = cfg, seq, tracker
        self._gt = seq.groundtruth() if groundtruth and getattr(seq, "sensor", "") != "mono" else None
        self._max_diff = max_diff
        self._pos: list[np.ndarray] = []  # camera centres of the frames with a pose, world metres
        self._map_ids: list[int] = []
        self._n_full = 0  # positions in the last full trajectory logged
        self._n_frames = 0
        self._n_loops = self._n_merges = 0
        self._map_id: int | None = None
        self.rec = rr.RecordingStream("vslam", recording_id=uuid.uuid4())
        sinks: list[Any] = []
        if cfg.rrd:
            Path(cfg.rrd).expanduser().parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(Path(cfg.rrd).expanduser())))
        if cfg.spawn:
            if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
                raise ConfigError("--viewer needs a display (DISPLAY / WAYLAND_DISPLAY unset); record with --rrd FILE "
                                  "or watch in a browser with --serve")
            exe = Path(sys.executable).with_name("rerun")  # the venv's viewer, whatever PATH holds
            port = cfg.grpc_port + 1 if cfg.serve else cfg.grpc_port  # (with serve, grpc_port is the server's)
            try:
                rr.spawn(port=port, connect=False, executable_path=str(exe) if exe.exists() else None,
                         recording=self.rec)
            except Exception as e:  # no viewer binary
                raise ConfigError(f"cannot start the Rerun viewer ({e}); record with --rrd FILE or use --serve") from None
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
        if cfg.serve:
            server = rr.GrpcServerSink(port=cfg.grpc_port)
            sinks.append(server)
        self.rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        if cfg.serve:
            rr.serve_web_viewer(web_port=cfg.web_port, open_browser=False, connect_to=server.uri)
            log.info("Rerun web viewer: %s", web_viewer_url(cfg))
        self.rec.send_recording_name(seq.name)
        self._log_static()

    # -- setup ---------------------------------------------------------------------
    def _blueprint(self) -> Any:
        rrb = self.rr.blueprint
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="3D"),
            rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="image"),
                         rrb.TimeSeriesView(origin="stats/ms", name="ms per stage"),
                         rrb.TimeSeriesView(origin="stats/count", name="counts"),
                         rrb.TextLogView(origin="/", name="status")),
            column_shares=[3, 2]), collapse_panels=True)

    def _log_static(self) -> None:
        rr, cam = self.rr, self.seq.calibration.cam0
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.rec.log("world/camera/image", rr.Pinhole(image_from_camera=cam.K, resolution=[cam.width, cam.height],
                                                      camera_xyz=rr.ViewCoordinates.RDF), static=True)

    def _log_groundtruth(self, T_world_cam: np.ndarray, t: float) -> None:
        """The ground truth in the run's world frame: moved so that its pose at ``t`` is this estimate's (the first
        estimate with a ground-truth pose within ``max_diff``; tried on the first 100 poses)."""
        gt = self._gt
        if gt is None or not len(gt) or len(self._pos) > 100:
            self._gt = None
            return
        i = int(np.argmin(np.abs(gt.timestamps - t)))
        if abs(gt.timestamps[i] - t) > self._max_diff:
            return
        self._gt = None
        T = T_world_cam @ np.linalg.inv(gt.poses[i])
        xyz = gt.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
        self.rec.log("world/trajectory/groundtruth", self.rr.LineStrips3D([xyz], colors=[(150, 150, 150)]), static=True)

    # -- per frame -----------------------------------------------------------------
    def log_frame(self, frame: Frame, est: Any, row: dict[str, Any]) -> None:
        """One frame: ``est`` its ``FrameEstimate``, ``row`` its stats.csv row (``vslam.pipeline.STAT_COLUMNS``)."""
        t0 = time.perf_counter()
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(frame.index))
        t = float(frame.timestamp)  # Unix time (TUM, EuRoC, bags) shown as a date, else seconds from 0
        rec.set_time("time", timestamp=t) if t > 1e8 else rec.set_time("time", duration=t)
        self._log_image(frame)
        if est.has_pose:
            T = est.T_world_cam
            if self._gt is not None:
                self._log_groundtruth(T, frame.timestamp)
            rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            self._pos.append(T[:3, 3].copy())
            self._map_ids.append(int(est.map_id))
        if self._map_id is not None and est.map_id != self._map_id:
            rec.log("events", rr.TextLog(f"frame {frame.index}: map {est.map_id} starts", level="WARN"))
        self._map_id = est.map_id
        self._n_frames += 1
        events = self._log_events()
        if self._n_frames % self.cfg.map_every == 1 or self.cfg.map_every == 1 or events:
            self._log_map()
        else:
            self._log_recent()
        self._log_row(row, est)
        rec.log("stats/ms/viewer", rr.Scalars((time.perf_counter() - t0) * 1e3))

    def _log_image(self, frame: Frame) -> None:
        rr, rec, img = self.rr, self.rec, frame.image
        if self.cfg.jpeg_quality > 0:
            _, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.jpeg_quality])
            # a uint8 array, not bytes: rerun converts bytes element by element (docs/speed.md)
            rec.log("world/camera/image", rr.EncodedImage(contents=buf.reshape(-1), media_type="image/jpeg"))
        else:
            rec.log("world/camera/image", rr.Image(img, color_model="BGR" if img.ndim == 3 else "L"))
        view = getattr(self.tracker, "view", None)
        if view is not None:
            fate = keypoint_fates(view)
            raw = view.front.feats.raw
            for f, name in enumerate(FATE_NAMES):
                rec.log(f"world/camera/image/keypoints/{name}",
                        rr.Points2D(raw[fate == f], colors=FATE_COLORS[f], radii=2.5))
            if view.front.objects is not None:
                rec.log("world/camera/image/boxes/detector",
                        rr.Boxes2D(array=np.asarray(view.front.objects.boxes).reshape(-1, 4), array_format=rr.Box2DFormat.XYXY,
                                   colors=(235, 40, 40)))
            if view.front.lines is not None:
                rec.log("world/camera/image/lines",
                        rr.LineStrips2D(np.asarray(view.front.lines.raw).reshape(-1, 2, 2), colors=(60, 160, 255)))
        if frame.boxes is not None:
            rec.log("world/camera/image/boxes/dataset",
                    rr.Boxes2D(array=np.asarray(frame.boxes).reshape(-1, 4), array_format=rr.Box2DFormat.XYXY,
                               colors=(255, 140, 0)))
        if frame.dynamic_mask is not None:
            rec.log("world/camera/image/dynamic_mask", rr.SegmentationImage(frame.dynamic_mask.astype(np.uint8),
                                                                            opacity=0.35))

    def _log_row(self, row: dict[str, Any], est: Any) -> None:
        rr, rec = self.rr, self.rec
        for key, v in row.items():
            if key.startswith("ms_") and isinstance(v, (int, float)):
                rec.log(f"stats/ms/{key[3:]}", rr.Scalars(float(v)))
        for key in COUNT_COLUMNS:
            if isinstance(row.get(key), (int, float)):
                rec.log(f"stats/count/{key[2:]}", rr.Scalars(float(row[key])))
        for key, name in (("pose_std_m", "m"), ("pose_std_deg", "deg")):
            v = row.get(key)
            if isinstance(v, float) and np.isfinite(v):
                rec.log(f"stats/pose_std/{name}", rr.Scalars(v))
        text = f"{est.status_name}: {est.n_inliers} inliers of {est.n_features} keypoints"
        rec.log("status", rr.TextLog(text, level="WARN" if est.uncertain else "INFO"))

    def _log_recent(self) -> None:
        """The trajectory since the last full one, joined to it (a full refresh is O(frames))."""
        a = max(self._n_full - 1, 0)
        pos, ids = np.array(self._pos[a:]).reshape(-1, 3), np.array(self._map_ids[a:])
        self.rec.log("world/trajectory/recent", self.rr.LineStrips3D(_strips(pos, ids), colors=(40, 120, 255)))

    def _log_map(self) -> None:
        rr, rec = self.rr, self.rec
        pos, ids = np.array(self._pos).reshape(-1, 3), np.array(self._map_ids)
        rec.log("world/trajectory/estimated", rr.LineStrips3D(_strips(pos, ids), colors=(40, 120, 255)))
        self._n_full = len(pos)
        m = getattr(self.tracker, "map", None)
        if m is None:
            return
        xyz = np.array([p.xyz for p in m.points.values()]).reshape(-1, 3)
        rec.log("world/map/points", rr.Points3D(xyz, colors=(200, 200, 200), radii=0.01))
        kf = np.array([k.T_world_cam[:3, 3] for k in m.keyframes.values()]).reshape(-1, 3)
        rec.log("world/map/keyframes", rr.Points3D(kf, colors=(255, 0, 255), radii=0.03))

    def _log_events(self) -> bool:
        """Loop closures and map merges since the last frame, as keyframe pairs; True if there were any."""
        loop = getattr(self.tracker, "loop", None)
        loops = list(loop.stats.loops) if loop is not None else []
        atlas = getattr(self.tracker, "atlas", None)
        merges = [(q, c) for _, _, q, c in atlas.merges] if atlas is not None else []
        if len(loops) == self._n_loops and len(merges) == self._n_merges:
            return False
        for name, pairs, n_before in (("loops", loops, self._n_loops), ("merges", merges, self._n_merges)):
            for a, b in pairs[n_before:]:
                self.rec.log("events", self.rr.TextLog(f"{name[:-1]}: keyframe {a} - keyframe {b}", level="INFO"))
            kfs = self.tracker.map.keyframes
            seg = [[kfs[a].T_world_cam[:3, 3], kfs[b].T_world_cam[:3, 3]] for a, b in pairs if a in kfs and b in kfs]
            if len(pairs) > n_before:
                self.rec.log(f"world/map/{name}", self.rr.LineStrips3D(seg, colors=(255, 60, 60) if name == "loops"
                                                                        else (255, 160, 0), radii=0.01))
        self._n_loops, self._n_merges = len(loops), len(merges)
        return True

    def close(self) -> None:
        """The final map and trajectory (at the last frame's time), then the sinks are flushed and closed."""
        try:
            if self._n_frames:
                self._log_map()
        finally:
            self.rec.disconnect()
