"""The SLAM system for one sequence: tracking + local mapping, a new map when tracking is lost (``Atlas``).

``SlamTracker(calibration, sensor, cfg).track(frame)`` returns the same
``FrameEstimate`` as the baseline odometry, so the pipeline swaps them by
config. Deterministic: a keyframe is mapped (points, fusion, culling, local BA)
before the next frame is tracked, or, with ``mapping.ba_lag_frames`` > 0, its
local BA runs in a second process and is written back (with the loop step that
follows it) a fixed number of frames later, never after the next keyframe.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from vslam.data.types import Calibration, Frame, SensorKind
from vslam.features import Features, make_extractor
from vslam.features.depth import stereo_ur
from vslam.geometry.se3 import inv_T
from vslam.mapping.local_mapping import LocalMapper
from vslam.mapping.map import Map
from vslam.runtime import RuntimeConfig
from vslam.tracking.atlas import Atlas
from vslam.tracking.baseline import FrameEstimate
from vslam.tracking.config import SlamConfig
from vslam.tracking.frame_log import FrameLog
from vslam.tracking.frontend import FrameView, FrontEnd, FrontEndMaker, sensor_rig
from vslam.tracking.map_steps import MapSteps
from vslam.tracking.mono_init import MonoInitializer
from vslam.tracking.recovery import MapRecovery
from vslam.tracking.stages import Stage, build_stages
from vslam.tracking.tracker import Tracker

log = logging.getLogger(__name__)


# FrameView and FrontEnd live in vslam.tracking.frontend; named here too because viewers and the front-end
# process meet them as what SlamTracker gives
__all__ = ["FrameView", "FrontEnd", "SlamConfig", "SlamTracker"]


class SlamTracker(MapRecovery, MapSteps):
    """Feed frames in order with ``track(frame)``; ``finish(out_dir)`` writes the keyframes and the map."""

    def __init__(self, calibration: Calibration, sensor: SensorKind, cfg: SlamConfig = SlamConfig(),
                 detector: object | None = None, runtime: RuntimeConfig = RuntimeConfig()):
        """``detector``: an object with ``detect(image) -> Detections`` that replaces the configured network of
        ``slam.dynamic`` (source=detector): a user's own detector, or a test's oracle. ``runtime``: how the
        front end uses the machine (``RuntimeConfig.lines_beside_networks``)."""
        self.calib, self.sensor, self.cfg, self.runtime = calibration, sensor, cfg, runtime
        self.cam = calibration.cam0
        self.baseline, self.rectified, self.stereo_cam = sensor_rig(calibration, sensor, cfg)
        self.extractor = make_extractor(cfg.features)
        if cfg.loop.enabled and cfg.loop.descriptor == "bow" and self.extractor.descriptor_kind != "binary":
            from vslam.errors import ConfigError

            raise ConfigError(f"slam.loop.descriptor: bow needs binary (ORB) keypoint descriptors, features.extractor is "
                              f"'{cfg.features.extractor}' (use slam.loop.descriptor=vladnet)")
        self.map = Map()
        self.frames = FrameLog(self.map)  # for trajectory_final: frames follow their keyframes (final_poses)
        self.tracker = Tracker(self.map, self.cam, self.stereo_cam, cfg.tracking, cfg.backend)
        # visual-inertial BA couples the keyframes through the IMU chain as it is built: solved at once
        mapping = replace(cfg.mapping, ba_lag_frames=0) if cfg.inertial.enabled else cfg.mapping
        self.mapper = LocalMapper(self.map, self.cam, self.stereo_cam, sensor, mapping, cfg.backend)
        self.mono_init = MonoInitializer(self.cam, cfg.init) if sensor == "mono" else None
        self.stages: list[Stage] = build_stages(self, detector)  # the optional parts (``vslam.tracking.stages``)
        self.mapper.inertial = self.vio
        self.front_end = FrontEndMaker(self.extractor, calibration, sensor, cfg, self.rectified,
                                       self._stage("lines"), self.dynamic)
        # New maps need a map to grow (not localize_only). Monocular-inertial maps take their scale and gravity
        # from the IMU initialisation, which would have to run again for every map: not built, the IMU bridges.
        self.map_id = 0
        self.atlas = (Atlas(cfg.atlas, self.cam, self.stereo_cam, cfg.tracking, cfg.backend)
                      if cfg.atlas.enabled and not cfg.localize_only and (self.vio is None or sensor != "mono")
                      else None)
        if self.atlas is not None:  # frames referenced to keyframes of an archived map follow them there
            self.frames.archived = self.atlas.maps
        if cfg.load_map:  # the saved map replaces the empty one everywhere it is referenced
            from vslam.loop.closing import attach_saved_map

            attach_saved_map(self, cfg.load_map)
        self._t_tracked: float | None = None  # time of the last tracked frame
        self._restart: np.ndarray | None = None  # a map was lost and no new one started yet: the pose it starts at
        self._lost_for_now = 0.0  # seconds since the last tracked frame, at the last frame not tracked
        self._n_lost = 0  # frames not tracked in a row
        self._t_last: float | None = None  # time of the last frame, and the interval before it (0: unknown)
        self._dt_last = 0.0
        self.T_world_cam = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last tracked step
        self.ref_kf: int | None = None
        self.last_kf_frame = 0
        self._prev_tracked = False
        self._last_ids: np.ndarray | None = None  # map points tracked in the last tracked frame (first round)
        self.n_frames = 0
        self._pre_init: list[tuple[int, Features]] = []  # monocular: (frame index, keypoints) before the map
        # (keyframe, its image, frame count) whose local BA the worker is solving and whose loop step waits for it
        self._pending: tuple | None = None
        self._rel_scale = 1.0  # a monocular loop's scale at the keyframe, for the frame tracked after it
        self.view: FrameView | None = None  # the last frame as tracking saw it (read-only, for vslam.viz)

    # -- the stages ----------------------------------------------------------------
    def _stage(self, name: str) -> Stage | None:
        return next((s for s in self.stages if s.name == name), None)

    def _part(self, stage: str, attr: str):
        st = self._stage(stage)
        return getattr(st, attr) if st is not None else None

    @property
    def loop(self):
        """The loop closer (``vslam.loop.closing.LoopCloser``: place database, relocalisation, loop correction),
        None with loop closing off."""
        return self._part("loop", "loop")

    @property
    def vio(self):
        """The visual-inertial state (``vslam.tracking.vio.Vio``), None without an IMU."""
        return self._part("inertial", "vio")

    @property
    def lines(self):
        """The line map of the current map (``vslam.mapping.line_map.LineSlam``), None with lines off."""
        return self._part("lines", "lines")

    @property
    def dynamic(self):
        """The dynamic-object filter (``vslam.dynamic.DynamicFilter``), None when off."""
        return self._part("dynamic", "dynamic")

    @property
    def dense(self):
        """The RGB-D depth tracker (``vslam.tracking.dense.DenseOdometry``), None when off."""
        return self._part("dense", "dense")

    # -- per-frame --------------------------------------------------------------
    def frontend(self, frame: Frame) -> FrontEnd:
        """The image-only part of ``track`` (``vslam.tracking.frontend``); safe to run on one other thread while
        ``track`` runs (the extractors are then used by that thread alone, the map is not read)."""
        return self.front_end.make(frame)

    def track(self, frame: Frame, front: FrontEnd | None = None) -> FrameEstimate:
        """One frame; ``front``: its ``frontend(frame)`` if computed ahead (else computed here)."""
        for s in self.stages:
            s.on_frame(frame)
        if front is None:
            front = self.frontend(frame)
        feats, lines, kept = front.feats, front.lines, None
        for s in self.stages:
            feats, lines, k = s.filter(frame, front, feats, lines)
            if k is not None:  # indices into what the previous filter kept
                kept = k if kept is None else kept[k]
        self.view = FrameView(front, kept)
        for s in self.stages:
            s.on_features(self, frame, feats, lines)
        t1 = time.perf_counter()
        # depth computed ahead holds every keypoint; after a filter it is measured on those left (rectified
        # stereo matching depends on which they are)
        depth = front.depth if front.depth is not None and kept is None else self.front_end.depth(frame, feats, front.right)
        ur = stereo_ur(feats.uv, depth, self.cam.fx, self.baseline) if self.baseline > 0 else np.full(len(feats), np.nan)
        ms_map: dict[str, float] = {}
        ms_flush = 0.0  # (features are extracted while the worker may still be solving)
        if self._pending is not None and self.n_frames - self._pending[2] >= self.mapper.cfg.ba_lag_frames:
            ms_map = self._flush_mapping()  # the worker's BA is due: tracking goes on from the adjusted map
            ms_flush = ms_map["flush"]
        t2 = time.perf_counter()
        est = FrameEstimate(self.T_world_cam, tracked=False, n_features=len(feats))
        for s in self.stages:
            s.annotate(est)
        if self.ref_kf is None:
            self._without_map(frame, feats, depth, ur, est)
            t3 = time.perf_counter()
        else:
            T_pred = self.T_world_cam @ self.velocity
            for s in self.stages:
                T_pred = s.predict(frame, T_pred)
            res = self._measure(frame, feats, ur, T_pred)
            self.view.point_ids = res.point_ids  # (``_drop_moving`` replaces, never edits, the array)
            est.n_matches, est.n_inliers, est.tracked = res.n_matches, res.n_inliers, res.ok
            est.status, est.pose_cov = self._status(res.ok, res.method, depth), res.cov
            if res.ok:
                if self._prev_tracked:  # a gap says nothing reliable about the per-frame motion
                    self.velocity = inv_T(self.T_world_cam) @ res.T_world_cam
                self.T_world_cam = res.T_world_cam
                self.ref_kf = self.tracker.best_reference(res.point_ids, self.ref_kf)
                self._last_ids = res.point_ids[res.point_ids >= 0]
            else:
                self._lost(frame, feats, depth, ur, T_pred, est)
            for s in self.stages:
                s.on_pose(self, frame, res.ok)
            for s in self.stages:
                feats, depth, ur = s.drop(self, res.ok, res, feats, depth, ur)
            t3 = time.perf_counter()
            stage_kf = any(s.wants_keyframe(frame, res, est.status) for s in self.stages)
            want = res.ok and not self.cfg.localize_only and (self._want_keyframe(frame, res.n_inliers, res.point_ids, depth, res.method) or stage_kf)
            if want and self._pending is not None:
                # The previous keyframe's BA lands first and the decision is taken again on the adjusted map:
                # decided on the stale one (its outlier observations still counted), keyframes came every
                # frame (TUM teddy, BA written back only at the next keyframe: tracking lost), and holding
                # keyframes back while BA runs (ORB-SLAM's "mapping busy") cost accuracy (docs/tracking.md,
                # "BA lag").
                ms_map = _add_ms(ms_map, self._flush_mapping())
                want = self._want_keyframe(frame, res.n_inliers, res.point_ids, depth, res.method) or stage_kf
            if want:
                kf = self.map.add_keyframe(frame.index, frame.timestamp, self.T_world_cam, feats, depth, ur)
                for s in self.stages:
                    s.on_keyframe(self, kf, frame, res)
                ms_map = _add_ms(ms_map, self.mapper.process(kf, res.point_ids))
                for s in self.stages:
                    s.after_mapping(self, kf)
                self.ref_kf, self.last_kf_frame = kf.id, self.n_frames
                if self.mapper.pending is not None:  # local BA in the worker; the loop step waits for it
                    self._pending = (kf, frame.image, self.n_frames)
                else:
                    ms_map = _add_ms(ms_map, self._after_local_ba(kf, frame.image))
                # local BA (and a loop correction) moved the keyframe: the frame's pose follows it
                self.T_world_cam = kf.T_world_cam.copy()
                ms_map = _add_ms(ms_map, self._try_merge(kf, frame.image))
        for s in self.stages:
            s.end_frame(self)
        t4 = time.perf_counter()
        if est.tracked:
            self._t_tracked = frame.timestamp
        self._n_lost = 0 if est.tracked else self._n_lost + 1
        self._dt_last = frame.timestamp - self._t_last if self._t_last is not None else 0.0
        self._t_last = frame.timestamp
        est.map_id = self.map_id
        self._prev_tracked = est.tracked
        self.n_frames += 1
        est.T_world_cam = self.T_world_cam.copy()
        self.frames.record(frame.index, self.ref_kf, self.T_world_cam)
        ms_map.pop("flush", None)
        # stage costs where they ran; those computed ahead on the prefetch thread are not in this call's time
        ms_depth = (t2 - t1) * 1e3 - ms_flush + (front.ms["depth"] if front.depth is not None and kept is None else 0.0)
        est.times_ms = {"features": front.ms["features"], "depth": ms_depth, "pose": (t3 - t2) * 1e3,
                        "mapping": (t4 - t3) * 1e3 + ms_flush, **{f"map_{k}": v for k, v in ms_map.items()}}
        for s in self.stages:
            s.report(est, front)
        return est

    # -- outputs ------------------------------------------------------------------
    def map_stats(self) -> dict[str, int]:
        stats = self.map.stats()
        for s in self.stages:
            stats.update(s.stats())
        return stats

    @property
    def metric_scale(self) -> bool:
        """Whether the trajectory is in metres: depth, a stereo baseline, or a monocular map the IMU has scaled.
        A run without it is scored with Sim3 (``EvalConfig.align: auto``)."""
        return self.sensor != "mono" or (self.vio is not None and self.vio.ready)

    def final_poses(self, frame_indices: list[int]) -> np.ndarray | None:
        """(F,4,4) poses of the frames through their reference keyframes when a loop correction or a monocular
        inertial rescale moved the map after they were written (``FrameLog``), else None (the online poses stand)."""
        moved = self.frames.moved or any(s.moved_map() for s in self.stages)
        return self.frames.poses(frame_indices) if moved else None

    def finish(self, out_dir: str | Path) -> dict[str, Path]:
        """Write ``keyframes.tum.txt`` (optimised keyframe poses) and ``map.ply`` (map points, world frame);
        with lines on also ``map_lines.ply`` (line set: two end points per map line)."""
        from vslam.data.trajectory import Trajectory, write_trajectory
        from vslam.outputs import write_map_ply

        for s in self.stages:
            if hasattr(s, "close"):
                s.close()
        if self._pending is not None:
            self._flush_mapping()
        self.mapper.close()
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = {}
        for s in self.stages:
            written.update(s.finish(self, out))
        kfs = sorted(self.map.keyframes.values(), key=lambda k: k.timestamp)
        stamps = np.array([k.timestamp for k in kfs], dtype=np.float64)
        poses = np.array([k.T_world_cam for k in kfs]).reshape(-1, 4, 4)
        paths = {"keyframes": write_trajectory(out / "keyframes.tum.txt", Trajectory(stamps, poses), "tum")}
        paths["map"] = write_map_ply(out / "map.ply", self.map.points_xyz(np.array(list(self.map.points), np.int64)))
        paths.update(written)
        if self.cfg.save_map:
            from vslam.loop.closing import save_slam_map

            paths["map_file"] = save_slam_map(self, out / "map.vslam.npz")
        log.info("map: %s", self.map_stats())
        return paths


def _add_ms(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    return {k: a.get(k, 0.0) + b.get(k, 0.0) for k in {**a, **b}}
