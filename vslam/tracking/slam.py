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
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import Calibration, Frame, SensorKind
from vslam.dynamic import DynamicConfig
from vslam.features import FeatureConfig, Features, make_extractor
from vslam.features.depth import stereo_ur
from vslam.features.lines import LineConfig
from vslam.features.stereo import is_rectified
from vslam.geometry.se3 import inv_T
from vslam.loop.config import LoopConfig
from vslam.mapping.local_mapping import LocalMapper, MappingConfig
from vslam.mapping.map import Map
from vslam.runtime import RuntimeConfig
from vslam.tracking.atlas import Atlas, AtlasConfig
from vslam.tracking.baseline import FrameEstimate
from vslam.tracking.dense import DenseConfig
from vslam.tracking.frame_log import FrameLog
from vslam.tracking.frontend import FrameView, FrontEnd, FrontEndMaker
from vslam.tracking.initializer import InitConfig
from vslam.tracking.mono_init import MonoInitializer
from vslam.tracking.stages import Stage, build_stages
from vslam.tracking.tracker import Tracker, TrackingConfig, TrackResult, need_keyframe
from vslam.tracking.vio import VioConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlamConfig:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)
    init_ba: bool = True  # monocular: BA of the two initial keyframes
    # monocular: once the map exists, localise the frames seen before it against the initial map (PnP); the
    # pipeline writes them into trajectory_final.tum.txt (trajectory.tum.txt keeps what was known per frame)
    backfill: bool = True
    loop: LoopConfig = field(default_factory=LoopConfig)  # loop closing + place relocalisation (vslam.loop)
    load_map: str = ""  # start from a map saved by save_map (vslam.loop.mapio)
    localize_only: bool = False  # with load_map: track against the saved map, never add keyframes
    save_map: bool = False  # finish() also writes map.vslam.npz (keyframes, points, place descriptors)
    inertial: VioConfig = field(default_factory=VioConfig)  # visual-inertial mode (vslam.tracking.vio), off by default
    lines: LineConfig = field(default_factory=LineConfig)  # point + Plücker-line features, off by default
    dynamic: DynamicConfig = field(default_factory=DynamicConfig)  # dynamic-object filtering, off by default
    dense: DenseConfig = field(default_factory=DenseConfig)  # RGB-D: depth ICP where features fail (tracking.dense)
    # tracking lost: a new map, and maps merged where they meet (``vslam.tracking.atlas``)
    atlas: AtlasConfig = field(default_factory=AtlasConfig)


# FrameView and FrontEnd live in vslam.tracking.frontend; named here too because viewers and the front-end
# process meet them as what SlamTracker gives
__all__ = ["FrameView", "FrontEnd", "SlamConfig", "SlamTracker", "write_map_ply"]


class SlamTracker:
    """Feed frames in order with ``track(frame)``; ``finish(out_dir)`` writes the keyframes and the map."""

    def __init__(self, calibration: Calibration, sensor: SensorKind, cfg: SlamConfig = SlamConfig(),
                 detector: object | None = None, runtime: RuntimeConfig = RuntimeConfig()):
        """``detector``: an object with ``detect(image) -> Detections`` that replaces the configured network of
        ``slam.dynamic`` (source=detector): a user's own detector, or a test's oracle. ``runtime``: how the
        front end uses the machine (``RuntimeConfig.lines_beside_networks``)."""
        self.calib, self.sensor, self.cfg, self.runtime = calibration, sensor, cfg, runtime
        self.cam = calibration.cam0
        if sensor == "stereo":
            if calibration.cam1 is None or calibration.baseline is None:
                raise ValueError("stereo SLAM needs cam1 and its extrinsics in the calibration")
            baseline = float(calibration.baseline)
        elif sensor == "rgbd":
            baseline = cfg.backend.rgbd_virtual_baseline
        else:
            baseline = 0.0
        self.baseline = baseline
        # the disparity's own noise where it is measured apart from the keypoint: a depth sensor, or the
        # sub-pixel stereo refinement of a rectified rig (``vslam.features.stereo``)
        self.rectified = sensor == "stereo" and cfg.tracking.stereo_refine and is_rectified(calibration)
        disparity_sigma = 0.0
        if sensor == "rgbd":
            disparity_sigma = cfg.backend.rgbd_disparity_sigma
        elif self.rectified:
            disparity_sigma = cfg.backend.stereo_disparity_sigma
        self.stereo_cam = StereoCamera(self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy, baseline, disparity_sigma)
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
        self.loop = None
        if cfg.loop.enabled or cfg.load_map:
            from vslam.loop.closing import LoopCloser, attach_saved_map

            self.loop = LoopCloser(self.map, self.cam, self.stereo_cam, sensor, cfg.loop, cfg.backend, self.mapper)
            self.loop.frames = self.frames
            if cfg.load_map:  # the saved map replaces the empty one everywhere it is referenced
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
            est.tracked = self._initialize(frame, feats, depth, ur, self._restart)
            for s in self.stages:
                s.drop(self, est.tracked, None, feats, depth, ur)
            est.status = "tracked" if est.tracked else "uninitialised"
            if self._restart is not None:
                # between two maps: no pose was measured ("lost", the last one held), or the new map starts here
                est.status = "new_map" if est.tracked else "lost"
                if est.tracked:
                    self._restart = None
                    est.pose_cov = np.zeros((6, 6))
                    if self.atlas.maps:  # type: ignore[union-attr]
                        self._try_merge(self.map.keyframes[self.ref_kf], frame.image)
                else:  # monocular, no new map yet: the camera may be back in a map it left
                    res = self._relocalise_archived(frame, feats, ur)
                    if res is not None:
                        est.tracked, est.status, est.pose_cov = True, res.method, res.cov
                        est.n_matches, est.n_inliers = res.n_matches, res.n_inliers
            if est.status == "relocalised":
                pass  # an archived map continues: its frames were localised when it was built
            elif self.mono_init is not None and self.cfg.backfill and not self.cfg.load_map:  # saved keyframes are not this run's frames
                if est.tracked:
                    est.backfill = self._backfill()
                else:  # the initialiser retries for max_tries frames per reference: older frames share little
                    self._pre_init = self._pre_init[-self.mono_init.max_tries:] + [(frame.index, feats)]
            if est.tracked and self.mono_init is None:
                est.pose_cov = np.zeros((6, 6))  # the first frame defines the world frame: exact by definition
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
                elif self.loop is not None:
                    ms_map = _add_ms(ms_map, self._loop_step(kf, frame.image))
                # local BA (and a loop correction) moved the keyframe: the frame's pose follows it
                self.T_world_cam = kf.T_world_cam.copy()
                if self.atlas is not None and self.atlas.maps:
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

    def _loop_step(self, kf, image: np.ndarray) -> dict[str, float]:
        """Place recognition (and a loop correction) for a mapped keyframe."""
        t = time.perf_counter()
        self.loop.add_keyframe(kf, image)  # type: ignore[union-attr]
        if self.loop.last_scale != 1.0:  # type: ignore[union-attr]  # a monocular loop rescaled this part of the map
            self.velocity = self.velocity.copy()
            self.velocity[:3, 3] *= self.loop.last_scale  # type: ignore[union-attr]
            self._rel_scale = self.loop.last_scale  # type: ignore[union-attr]
            self.loop.last_scale = 1.0  # type: ignore[union-attr]
        return {"loop": (time.perf_counter() - t) * 1e3}

    def _flush_mapping(self) -> dict[str, float]:
        """Write back the worker's local BA, then run the loop step that waited for it; the current pose follows
        the keyframe (as the keyframe's own pose does when BA runs at once). -> ms per step, "flush" the total."""
        t = time.perf_counter()
        kf, image, _ = self._pending  # type: ignore[misc]
        self._pending = None
        T_before = kf.T_world_cam.copy()
        ms = {"wait": self.mapper.flush()}
        self._rel_scale = 1.0
        if self.loop is not None:
            ms.update(self._loop_step(kf, image))
        rel = inv_T(T_before) @ self.T_world_cam
        rel[:3, 3] *= self._rel_scale
        self.T_world_cam = kf.T_world_cam @ rel
        ms["flush"] = (time.perf_counter() - t) * 1e3
        return ms

    def _backfill(self) -> dict[int, np.ndarray]:
        """Monocular, right after the two-view initialisation: poses of the frames seen before it, by descriptor
        matching + PnP + pose-only refinement against the initial map (``Tracker.track_keyframe`` on the first
        keyframe; frames between the two views see its points). -> {frame index: T_world_cam}; frames that do
        not localise are left out."""
        from scipy.spatial import cKDTree

        kf0 = self.map.keyframes[min(self.map.keyframes)]  # the reference view defines the world
        out = {kf0.frame_index: kf0.T_world_cam.copy()}
        for idx, feats in self._pre_init:
            if idx in out or len(feats) < self.cfg.tracking.min_inliers:
                continue
            res = self.tracker.track_keyframe(feats, np.full(len(feats), np.nan), kf0.id, cKDTree(feats.uv), "backfill")
            if res is not None and res.ok:
                out[idx] = res.T_world_cam
        self._pre_init = []
        for idx, T in out.items():  # they follow kf0 when the map moves later (loop, mono-inertial scale)
            self.frames.record(idx, kf0.id, T)
        return out

    def _initialize(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray,
                    T0: np.ndarray | None = None) -> bool:
        """Start the map (RGB-D / stereo: this frame's depth, its keyframe at ``T0``, the identity for the first
        map; monocular: the two-view initialiser)."""
        if self.cfg.load_map:  # a saved map: the first frame is placed in it by place recognition
            res = self.loop.relocalise(self.tracker, feats, ur, frame.image)  # type: ignore[union-attr]
            if res is None:
                return False
            self.T_world_cam, self.ref_kf = res.T_world_cam, self.tracker.best_reference(res.point_ids, -1)
            return self.ref_kf >= 0
        if self.mono_init is not None:
            kfs = self.mono_init.try_initialize(self.map, frame.index, frame.timestamp, feats, self.stereo_cam,
                                                self.cfg.backend, self.cfg.init_ba)
            if kfs is None:
                return False
            self.ref_kf, self.last_kf_frame = kfs[1].id, self.n_frames
            self.T_world_cam = kfs[1].T_world_cam.copy()
            for s in self.stages:
                s.on_two_view_map(self, kfs, frame)
            if self.loop is not None:  # the reference view's image is gone: an image descriptor sees only the second
                for k in kfs:
                    self.loop.add_keyframe(k, frame.image if k is kfs[1] else None)
            return True
        if int(np.isfinite(depth).sum()) < self.cfg.tracking.min_depth_points:
            return False
        T0 = np.eye(4) if T0 is None else T0
        kf = self.map.add_keyframe(frame.index, frame.timestamp, T0, feats, depth, ur)
        for s in self.stages:
            s.on_keyframe(self, kf, frame, None)
        self.mapper.process(kf, np.full(len(feats), -1, np.int64))
        if self.loop is not None:
            self.loop.add_keyframe(kf, frame.image)
        self.ref_kf, self.last_kf_frame = kf.id, self.n_frames
        self.T_world_cam = T0.copy()
        return True

    # -- the tracking states -------------------------------------------------------
    @property
    def state(self) -> str:
        """Where tracking stands after the last frame: "initialising" (no map yet), "tracking" (the frame was
        measured), "lost" (not measured: predicted while every recovery step is tried on the next frames),
        "relocalising" (lost for ``atlas.new_map_after_s``: a new map starts at the first frame that can make
        one, the old map is still tried until then), "new_map" (a monocular map was given up; the next two-view
        initialisation starts the new one)."""
        if self._restart is not None:
            return "new_map"
        if self.ref_kf is None:
            return "initialising"
        if self._prev_tracked:
            return "tracking"
        return "relocalising" if self._lost_for_now >= self.cfg.atlas.new_map_after_s else "lost"

    def _measure(self, frame: Frame, feats: Features, ur: np.ndarray, T_pred: np.ndarray) -> TrackResult:
        """The recovery ladder, each step only when the ones before failed: the motion model's projection search,
        the reference keyframe by descriptor, after a loss the newest keyframes (``Tracker.track``); place
        relocalisation over the whole map (``slam.loop``); the dense depth step (RGB-D, ``slam.dense``)."""
        wide = self._t_tracked is not None and frame.timestamp - self._t_tracked >= self.cfg.tracking.wide_gap_s
        res = self.tracker.track(feats, ur, T_pred, self.ref_kf, after_loss=not self._prev_tracked,  # type: ignore[arg-type]
                                 last_ids=self._last_ids, wide=wide)
        if not res.ok and self.loop is not None and self.cfg.loop.relocalise:  # place recognition over all keyframes
            res = self.loop.relocalise(self.tracker, feats, ur, frame.image) or res
        for s in self.stages:  # lines refine a tracked pose; dense depth tracking tries a lost one
            res = s.measure(self, frame, feats, ur, T_pred, res)
        if not res.ok:  # the camera may be back in a map it left: that map continues
            res = self._relocalise_archived(frame, feats, ur) or res
        return res

    def _lost(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray, T_pred: np.ndarray,
              est: FrameEstimate) -> None:
        """A frame no recovery step measured: predicted (motion model) at first; once lost for
        ``atlas.new_map_after_s`` a new map from this frame if it can make one; past ``atlas.bridge_s`` no pose."""
        T_last = self.T_world_cam
        self.T_world_cam = T_pred
        log.debug("frame %d not tracked; pose predicted", frame.index)
        lost_s = self._lost_for_now = self._lost_for(frame.timestamp)
        # after a gap in the images (3 frame intervals or more) nothing is gained by waiting for another frame
        gap = self._dt_last > 0 and frame.timestamp - self._t_last > 3 * self._dt_last  # type: ignore[operator]
        if lost_s >= self.cfg.atlas.new_map_after_s and (self._n_lost + 1 >= self.cfg.atlas.min_lost_frames or gap):
            # the new map's frame continues the old one's: from where the IMU puts the camera, else where it was
            # last seen
            T0 = T_pred if self.vio is not None and self.vio.predicting else T_last
            if self._new_map(frame, feats, depth, ur, T0):
                est.tracked, est.status, est.pose_cov = True, "new_map", np.zeros((6, 6))
            elif lost_s > self.cfg.atlas.bridge_s:
                est.status = "lost"  # predicted no longer: no pose
                self.T_world_cam = T_last

    # -- several maps (``vslam.tracking.atlas``) -----------------------------------
    def _lost_for(self, t: float) -> float:
        """Seconds since the last tracked frame; 0 while a new map cannot be made (no Atlas)."""
        return 0.0 if self.atlas is None or self._t_tracked is None else t - self._t_tracked

    def _use_map(self, m: Map) -> None:
        """Make ``m`` the map every stage works on."""
        self.map = self.tracker.map = self.mapper.map = self.frames.map = m
        self.mapper.recent = [p for p in self.mapper.recent if p in m.points]
        self._last_ids = None
        if self.loop is not None:
            self.loop.map = m
        for s in self.stages:
            s.on_map(self, m)

    def _new_map(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray, T0: np.ndarray) -> bool:
        """Archive the current map and start a new one: at once from this frame's depth (RGB-D / stereo; -> True
        when it did), at the next two-view initialisation (monocular)."""
        atlas = self.atlas
        assert atlas is not None
        if self.mono_init is None and int(np.isfinite(depth).sum()) < atlas.cfg.min_points:
            return False  # not enough depth for a map worth keeping (blur, a black frame): stay on the old one
        if self._pending is not None:
            self._flush_mapping()
        atlas.votes = []
        if atlas.descriptor is None and (atlas.cfg.merge or atlas.cfg.relocalise):
            atlas.descriptor = self._place_descriptor()
        if self.map.keyframes:
            old_db = self.loop.db if self.loop is not None else None
            atlas.archive(self.map_id, self.map, old_db)
            self.map_id = atlas.new_id()
        if self.loop is not None:
            from vslam.loop.database import KeyframeDatabase

            self.loop.db = KeyframeDatabase(self.loop.descriptor.dim)
            self.loop._groups = []
        self._use_map(self.map.successor())
        for s in self.stages:
            s.on_new_map()
        self.ref_kf, self.velocity, self._t_tracked = None, np.eye(4), None
        log.info("frame %d: tracking lost; map %d started", frame.index, self.map_id)
        if self.mono_init is None:
            return self._initialize(frame, feats, depth, ur, T0)
        self.mono_init = MonoInitializer(self.cam, self.cfg.init)
        self._pre_init = []
        self._restart = T0  # monocular: the next two-view initialisation starts the map (``track``)
        return False

    def _relocalise_archived(self, frame: Frame, feats: Features, ur: np.ndarray) -> TrackResult | None:
        """A frame the current map did not measure, looked for in the archived maps (``atlas.relocalise``); found,
        that map becomes the current one again (``_switch_map``) -> the frame's result there, method
        "relocalised". Not with an IMU: each map's inertial state is not kept when it is archived."""
        atlas = self.atlas
        if atlas is None or not atlas.maps or not atlas.cfg.relocalise or self.vio is not None:
            return None
        if atlas.descriptor is None:
            return None  # no place descriptor (learned keypoints without the loop closer)
        vec = atlas.describe(feats, frame.image)
        hit = atlas.locate(feats, ur, vec, atlas.cfg.relocalise_min_inliers, "relocalised",
                           self.cfg.tracking.ratio_wide)
        if hit is None:
            return None
        map_id, cand, res = hit
        self._switch_map(map_id)
        self.T_world_cam, self.velocity = res.T_world_cam, np.eye(4)  # the motion since the loss is unknown
        self.ref_kf = self.tracker.best_reference(res.point_ids, cand)
        self._last_ids = res.point_ids[res.point_ids >= 0]
        log.info("frame %d relocalised in map %d (keyframe %d, %d inliers)", frame.index, map_id, cand, res.n_inliers)
        return res

    def _switch_map(self, map_id: int) -> None:
        """Archived map ``map_id`` becomes the current one; the current map is archived (dropped when it has no
        keyframe yet) and any pending monocular re-initialisation is given up."""
        atlas = self.atlas
        assert atlas is not None
        if self._pending is not None:
            self._flush_mapping()
        m, db = atlas.take(map_id)
        m.continue_ids(self.map)  # ids stay unique across the run's maps
        if self.map.keyframes:
            atlas.archive(self.map_id, self.map, self.loop.db if self.loop is not None else None)
        if self.loop is not None:
            from vslam.loop.database import KeyframeDatabase

            self.loop.db = db if db is not None else KeyframeDatabase(self.loop.descriptor.dim)
            self.loop._groups = []
        self._use_map(m)
        self.map_id = map_id
        self._restart = None
        if self.mono_init is not None:
            self.mono_init = MonoInitializer(self.cam, self.cfg.init)
            self._pre_init = []
        atlas.switches += 1
        atlas.votes = []

    def _place_descriptor(self):
        """The keyframes' place descriptor for merging: the loop closer's, else the bag of words over ORB
        descriptors (None for learned float descriptors without the loop closer: maps are then never merged)."""
        if self.loop is not None:
            return self.loop.descriptor
        if self.extractor.descriptor_kind != "binary":
            log.warning("slam.atlas.merge needs slam.loop.enabled with learned keypoints; maps will not be merged")
            return None
        from vslam.loop.descriptor import make_place_descriptor

        return make_place_descriptor("bow", self.cfg.loop.vocabulary)

    def _try_merge(self, kf, image: np.ndarray) -> dict[str, float]:
        """Look for the new keyframe in the archived maps; on a confirmed match move this map into that one."""
        t = time.perf_counter()
        atlas = self.atlas
        assert atlas is not None
        vec = (self.loop.db.vector(kf.id) if self.loop is not None and kf.id in self.loop.db
               else atlas.describe(kf.features, image))
        hit = atlas.locate(kf.features, kf.ur, vec) if atlas.cfg.merge else None
        if hit is None:
            atlas.votes = []  # the keyframes that found an archived map must follow one another
        elif atlas.vote(hit[0], Atlas.old_from_new(kf.T_world_cam, hit[2].T_world_cam), self.sensor != "mono"):
            atlas.votes = []
            self._merge(kf, *hit)
        return {"merge": (time.perf_counter() - t) * 1e3}

    def _merge(self, kf, old_id: int, cand: int, res: TrackResult) -> None:
        """The current map joins archived map ``old_id``: moved by the transform the keyframe's two poses give
        (monocular: a similarity, ``Atlas.scale``), the seam's duplicate points fused into the keyframe and its
        neighbours, then a global BA."""
        atlas = self.atlas
        assert atlas is not None
        scale = 1.0
        if self.sensor == "mono":
            s = atlas.scale(atlas.maps[old_id], self.map, kf, res)
            if s is None:
                log.info("keyframe %d seen in map %d, too few points on both sides for the scale: not merged", kf.id, old_id)
                return
            scale = s
        T_old_new = atlas.old_from_new(kf.T_world_cam, res.T_world_cam, scale)
        if self.vio is not None and self.vio.ready:  # both maps in the IMU's gravity-aligned frame
            T_old_new = atlas.yaw_only(T_old_new, kf.T_world_cam)
        old, old_db = atlas.take(old_id)
        new, new_id = self.map, self.map_id
        if scale != 1.0:  # the frames' poses relative to their keyframes, and the motion model, take the old unit
            self.frames.scale_refs({k: scale for k in new.keyframes})
            self.velocity = self.velocity.copy()
            self.velocity[:3, 3] *= scale
        old.absorb(new, T_old_new, scale)
        if self.loop is not None and old_db is not None:  # one database for the merged map
            for k in old_db.ids().tolist():
                self.loop.db.add(k, old_db.vector(k))
        self._use_map(old)
        self.frames.moved = True  # the frames of the merged map are re-expressed in the old map's frame
        atlas.parent[new_id] = old_id
        atlas.merges.append((new_id, old_id, kf.id, cand))
        self.map_id = old_id
        old.fuse_matches(kf.id, res.point_ids)  # the keyframe's keypoints that matched the old map's points
        _, seam = old.local_map(cand, self.cfg.tracking.local_keyframes)
        for k in [kf.id, *old.covisible_keyframes(kf.id, 1, self.cfg.mapping.fuse_neighbors)]:
            self.mapper._fuse_into(old.keyframes[k], seam)
        old.update_descriptors(np.unique(kf.point_ids[kf.point_ids >= 0]))
        # as after a loop: every keyframe and point re-fitted across the seam, whose fused points now tie the maps
        from vslam.loop.closing import global_bundle_adjust

        lc = self.cfg.loop
        global_bundle_adjust(old, self.stereo_cam, self.cfg.backend, lc.global_ba_iterations, lc.global_ba_min_obs)
        self.T_world_cam = kf.T_world_cam.copy()
        log.info("map %d merged into map %d (keyframe %d seen in keyframe %d, %d inliers, scale %.3f)", new_id,
                 old_id, kf.id, cand, res.n_inliers, scale)

    def _status(self, ok: bool, method: str, depth: np.ndarray) -> str:
        """FrameEstimate.status of a frame after initialisation (see there)."""
        if not ok:
            return "predicted"
        if method in ("relocalised", "dense"):  # dense: the depth ICP of vslam.tracking.dense
            return method
        if self.sensor != "mono" and int(np.isfinite(depth).sum()) < self.cfg.tracking.min_depth_points:
            return "no_depth"  # measured from 2-D matches only: weaker, and the frame cannot become a keyframe
        return "tracked"

    def _want_keyframe(self, frame: Frame, n_inliers: int, point_ids: np.ndarray, depth: np.ndarray, method: str = "") -> bool:
        tc = self.cfg.tracking
        if self.sensor != "mono" and int(np.isfinite(depth).sum()) < tc.min_depth_points:
            return False  # a keyframe without depth would add no points
        for s in self.stages:  # a stage that measured the frame (depth ICP) has its own rule
            d = s.decides_keyframe(method, depth, tc.kf_min_inliers)
            if d is not None:
                return d
        ref = self.map.keyframes[self.ref_kf]  # type: ignore[index]
        min_obs = min(3, len(self.map.keyframes))  # ORB-SLAM: 2 while the map has <= 2 keyframes; 1 for the first
        ref_ids = ref.point_ids[ref.point_ids >= 0]
        points = self.map.points
        ref_tracked = sum(1 for p in ref_ids.tolist() if len(points[p].observations) >= min_obs)
        close = np.isfinite(depth) & (depth < tc.close_baselines * self.baseline)
        n_close_tracked = int(np.sum(close & (point_ids >= 0)))
        n_close_untracked = int(np.sum(close & (point_ids < 0)))
        return need_keyframe(n_inliers, ref_tracked, self.n_frames - self.last_kf_frame, n_close_tracked,
                             n_close_untracked, self.sensor, tc)

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
        moved = self.frames.moved or (self.loop is not None and self.loop.stats.corrected > 0)
        return self.frames.poses(frame_indices) if moved else None

    def final_map_ids(self, map_ids: list[int]) -> list[int]:
        """The map each of ``map_ids`` (the frames' maps when tracked) ended in after the merges."""
        if self.atlas is None:
            return list(map_ids)
        return [self.atlas.final_id(m) for m in map_ids]

    def recovery_stats(self) -> dict[str, int]:
        """new_maps (started after a loss), merges (maps joined into an older one), map_switches (frames
        relocalised into an archived map, which then continued)."""
        a = self.atlas
        if a is None:
            return {}
        return {"new_maps": a.n_maps - 1, "merges": len(a.merges), "map_switches": a.switches}

    def finish(self, out_dir: str | Path) -> dict[str, Path]:
        """Write ``keyframes.tum.txt`` (optimised keyframe poses) and ``map.ply`` (map points, world frame);
        with lines on also ``map_lines.ply`` (line set: two end points per map line)."""
        from vslam.data.trajectory import Trajectory, write_trajectory

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
        if self.loop is not None:
            paths["loops"] = self.loop.write_stats(out / "loops.json")
        if self.cfg.save_map:
            from vslam.loop.closing import save_slam_map

            paths["map_file"] = save_slam_map(self, out / "map.vslam.npz")
        log.info("map: %s", self.map_stats())
        return paths


def _add_ms(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    return {k: a.get(k, 0.0) + b.get(k, 0.0) for k in {**a, **b}}


def write_map_ply(path: Path, xyz: np.ndarray) -> Path:
    """(N,3) world points -> binary PLY point cloud (x, y, z doubles), the layout open3d writes. Written here, not
    by open3d: importing it for this costs resident memory at the end of every run (docs/speed.md)."""
    from vslam.outputs import atomic_open

    xyz = np.ascontiguousarray(xyz, dtype="<f8").reshape(-1, 3)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\nproperty double x\n"
            "property double y\nproperty double z\nend_header\n")
    with atomic_open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(xyz.tobytes())
    return path
