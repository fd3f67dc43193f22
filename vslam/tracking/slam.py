"""The SLAM system for one sequence: tracking + local mapping over one map.

``SlamTracker(calibration, sensor, cfg).track(frame)`` returns the same
``FrameEstimate`` as the baseline odometry, so the pipeline swaps them by
config. Single-threaded and deterministic: a keyframe is mapped (points, fusion,
culling, local BA) before the next frame is tracked.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import Calibration, Frame, SensorKind
from vslam.features import FeatureConfig, Features, make_extractor
from vslam.features.depth import depth_rgbd, depth_stereo, stereo_ur
from vslam.geometry.se3 import inv_T
from vslam.mapping.local_mapping import LocalMapper, MappingConfig
from vslam.mapping.map import Map
from vslam.tracking.baseline import FrameEstimate
from vslam.tracking.initializer import InitConfig
from vslam.tracking.mono_init import MonoInitializer
from vslam.tracking.tracker import Tracker, TrackingConfig, need_keyframe

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SlamConfig:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)
    init_ba: bool = True  # monocular: BA of the two initial keyframes


class SlamTracker:
    """Feed frames in order with ``track(frame)``; ``finish(out_dir)`` writes the keyframes and the map."""

    def __init__(self, calibration: Calibration, sensor: SensorKind, cfg: SlamConfig = SlamConfig()):
        self.calib, self.sensor, self.cfg = calibration, sensor, cfg
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
        self.stereo_cam = StereoCamera(self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy, baseline)
        self.extractor = make_extractor(cfg.features)
        self.map = Map()
        self.tracker = Tracker(self.map, self.cam, self.stereo_cam, cfg.tracking, cfg.backend)
        self.mapper = LocalMapper(self.map, self.cam, self.stereo_cam, sensor, cfg.mapping, cfg.backend)
        self.mono_init = MonoInitializer(self.cam, cfg.init) if sensor == "mono" else None
        self.T_world_cam = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last tracked step
        self.ref_kf: int | None = None
        self.last_kf_frame = 0
        self._prev_tracked = False
        self._n_frames = 0

    # -- per-frame --------------------------------------------------------------
    def _depth(self, frame: Frame, feats: Features) -> np.ndarray:
        tc = self.cfg.tracking
        if self.sensor == "rgbd":
            return depth_rgbd(frame.depth, feats, tc.min_depth, tc.max_depth)
        if self.sensor == "stereo" and frame.right is not None and len(feats):
            right = self.extractor.detect(frame.right, self.calib.cam1)  # type: ignore[arg-type]
            return depth_stereo(feats, right, self.calib, tc.min_depth, tc.max_depth, tc.stereo_max_px)
        return np.full(len(feats), np.nan)

    def track(self, frame: Frame) -> FrameEstimate:
        t0 = time.perf_counter()
        feats = self.extractor.detect(frame.image, self.cam)
        t1 = time.perf_counter()
        depth = self._depth(frame, feats)
        ur = stereo_ur(feats.uv, depth, self.cam.fx, self.baseline) if self.baseline > 0 else np.full(len(feats), np.nan)
        t2 = time.perf_counter()
        est = FrameEstimate(self.T_world_cam, tracked=False, n_features=len(feats))
        ms_map: dict[str, float] = {}
        if self.ref_kf is None:
            est.tracked = self._initialize(frame, feats, depth, ur)
            t3 = time.perf_counter()
        else:
            T_pred = self.T_world_cam @ self.velocity
            res = self.tracker.track(feats, ur, T_pred, self.ref_kf, after_loss=not self._prev_tracked)
            est.n_matches, est.n_inliers, est.tracked = res.n_matches, res.n_inliers, res.ok
            if res.ok:
                if self._prev_tracked:  # a gap says nothing reliable about the per-frame motion
                    self.velocity = inv_T(self.T_world_cam) @ res.T_world_cam
                self.T_world_cam = res.T_world_cam
                self.ref_kf = self.tracker.best_reference(res.point_ids, self.ref_kf)
            else:
                self.T_world_cam = T_pred
                log.debug("frame %d not tracked; pose predicted", frame.index)
            t3 = time.perf_counter()
            if res.ok and self._want_keyframe(frame, res.n_inliers, res.point_ids, depth):
                kf = self.map.add_keyframe(frame.index, frame.timestamp, self.T_world_cam, feats, depth, ur)
                ms_map = self.mapper.process(kf, res.point_ids)
                self.ref_kf, self.last_kf_frame = kf.id, self._n_frames
                # local BA moved the keyframe: the frame's pose follows it
                self.T_world_cam = kf.T_world_cam.copy()
        t4 = time.perf_counter()
        self._prev_tracked = est.tracked
        self._n_frames += 1
        est.T_world_cam = self.T_world_cam.copy()
        est.times_ms = {"features": (t1 - t0) * 1e3, "depth": (t2 - t1) * 1e3, "pose": (t3 - t2) * 1e3,
                        "mapping": (t4 - t3) * 1e3, **{f"map_{k}": v for k, v in ms_map.items()}}
        return est

    def _initialize(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray) -> bool:
        if self.mono_init is not None:
            kfs = self.mono_init.try_initialize(self.map, frame.index, frame.timestamp, feats, self.stereo_cam,
                                                self.cfg.backend, self.cfg.init_ba)
            if kfs is None:
                return False
            self.ref_kf, self.last_kf_frame = kfs[1].id, self._n_frames
            self.T_world_cam = kfs[1].T_world_cam.copy()
            return True
        if int(np.isfinite(depth).sum()) < self.cfg.tracking.min_depth_points:
            return False
        kf = self.map.add_keyframe(frame.index, frame.timestamp, np.eye(4), feats, depth, ur)
        self.mapper.process(kf, np.full(len(feats), -1, np.int64))
        self.ref_kf, self.last_kf_frame = kf.id, self._n_frames
        return True

    def _want_keyframe(self, frame: Frame, n_inliers: int, point_ids: np.ndarray, depth: np.ndarray) -> bool:
        tc = self.cfg.tracking
        if self.sensor != "mono" and int(np.isfinite(depth).sum()) < tc.min_depth_points:
            return False  # a keyframe without depth would add no points
        ref = self.map.keyframes[self.ref_kf]  # type: ignore[index]
        min_obs = min(3, len(self.map.keyframes))  # ORB-SLAM: 2 while the map has <= 2 keyframes; 1 for the first
        ref_ids = ref.point_ids[ref.point_ids >= 0]
        ref_tracked = sum(1 for p in ref_ids if len(self.map.points[int(p)].observations) >= min_obs)
        close = np.isfinite(depth) & (depth < tc.close_baselines * self.baseline)
        n_close_tracked = int(np.sum(close & (point_ids >= 0)))
        n_close_untracked = int(np.sum(close & (point_ids < 0)))
        return need_keyframe(n_inliers, ref_tracked, self._n_frames - self.last_kf_frame, n_close_tracked,
                             n_close_untracked, self.sensor, tc)

    # -- outputs ------------------------------------------------------------------
    def map_stats(self) -> dict[str, int]:
        return self.map.stats()

    def finish(self, out_dir: str | Path) -> dict[str, Path]:
        """Write ``keyframes.tum.txt`` (optimised keyframe poses) and ``map.ply`` (map points, world frame)."""
        from vslam.data.trajectory import Trajectory, write_trajectory

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        kfs = sorted(self.map.keyframes.values(), key=lambda k: k.timestamp)
        stamps = np.array([k.timestamp for k in kfs], dtype=np.float64)
        poses = np.array([k.T_world_cam for k in kfs]).reshape(-1, 4, 4)
        paths = {"keyframes": write_trajectory(out / "keyframes.tum.txt", Trajectory(stamps, poses), "tum")}
        paths["map"] = write_map_ply(out / "map.ply", self.map.points_xyz(np.array(list(self.map.points), np.int64)))
        log.info("map: %s", self.map_stats())
        return paths


def write_map_ply(path: Path, xyz: np.ndarray) -> Path:
    """(N,3) world points -> PLY point cloud (open3d imported here only: it is heavy and optional)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
    if not o3d.io.write_point_cloud(str(path), pcd):
        raise OSError(f"{path}: could not write the map")
    return path
