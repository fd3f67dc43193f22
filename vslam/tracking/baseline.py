"""Ground-truth-free frame-to-frame odometry: the clearly-labelled placeholder
front end until the SLAM core (tracking + local mapping + GTSAM back end) lands.

Each frame is matched (ORB, Hamming, mutual + ratio test) against a
reference frame, kept until the inliers against it drop below
``keyframe_ratio`` of what they were; 3-D points of that reference frame come from its
depth map (RGB-D) or from left-right triangulation (stereo), and the new pose
is a RANSAC PnP. Monocular falls back to the essential matrix with a unit
translation per step, so its scale is arbitrary (evaluate with Sim3). No map,
no bundle adjustment, no loop closing: drift accumulates.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from vslam.data.types import Calibration, Frame, PinholeCamera, SensorKind
from vslam.features.matching import match_mutual
from vslam.geometry.se3 import inv_T, make_T

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryConfig:
    n_features: int = 1500
    ratio: float = 0.8  # Lowe ratio for descriptor matching
    ransac_px: float = 2.0  # PnP / essential inlier threshold, pixels
    min_inliers: int = 20  # fewer -> the frame is "lost" and the pose is predicted
    min_depth: float = 0.1  # metres; depth outside [min, max] is ignored
    max_depth: float = 10.0
    stereo_max_epipolar_px: float = 1.5  # left-right match must lie this close to the epipolar line
    keyframe_ratio: float = 0.7  # a new reference frame when inliers drop below this fraction of the first
    seed: int = 0  # OpenCV RANSAC seed (cv2.setRNGSeed) so runs are repeatable


@dataclass
class FrameEstimate:
    """Result for one frame: pose (4,4) T_world_cam, whether it was measured or predicted, and stats."""

    T_world_cam: np.ndarray
    tracked: bool
    n_features: int = 0
    n_matches: int = 0
    n_inliers: int = 0
    # with line features (``slam.lines``): segments detected, and map lines kept by the pose refinement; None without
    n_lines: int | None = None
    n_line_inliers: int | None = None
    times_ms: dict[str, float] = field(default_factory=dict)
    # What the pose is (faulty frames are kept and marked): "tracked", "relocalised" (measured after a loss), "no_depth"
    # (RGB-D/stereo frame measured from 2-D matches only), "predicted" (constant velocity through a
    # failure), "uninitialised" (no map yet: placeholder pose), "new_map" (tracking was lost: a new map starts
    # at this frame, ``vslam.tracking.atlas``), "lost" (the old map was given up and no new one could start
    # yet: the last pose held), "dense" (RGB-D, features too few: measured by depth ICP against the reference
    # keyframe, ``vslam.tracking.dense``; all 6 degrees of freedom, frames whose geometry leaves one free are
    # refused). "" = derived from ``tracked``.
    status: str = ""
    # the map the pose is expressed in (a new one each time tracking is lost; merged maps keep the older id)
    map_id: int = 0
    # (6,6) covariance of the measured pose, (rotation rad, translation m) of the left perturbation of
    # T_cam_world (``vslam.backend.pose_only.pose_covariance``); None when not measured or not estimated.
    pose_cov: np.ndarray | None = None
    # poses of earlier frames measured late, by frame index (monocular frames before the map existed)
    backfill: dict[int, np.ndarray] = field(default_factory=dict)
    # the IMU on this frame (visual-inertial runs): "used", "off" (inertial factors off: samples missing or
    # rejected over this stretch, an IMU factor dropped as inconsistent with vision, or waiting for the keyframe
    # that restarts the IMU chain; ``vslam.inertial.health``), "" without an IMU
    imu: str = ""

    @property
    def uncertain(self) -> bool:
        """True when the pose was not measured from a full frame: predicted, uninitialised, no depth."""
        return self.status_name not in ("tracked", "relocalised", "new_map", "dense")

    @property
    def status_name(self) -> str:
        return self.status or ("tracked" if self.tracked else "predicted")

    @property
    def has_pose(self) -> bool:
        """False for a frame before any map ("uninitialised") or between two maps ("lost"): it is left out of
        the trajectory (a placeholder would read as a measured pose), and listed in stats.csv."""
        return self.status_name not in ("lost", "uninitialised")

    def pose_std(self) -> tuple[float, float]:
        """(position std m, rotation std deg) from ``pose_cov``: sqrt of the traces; NaN when unknown."""
        if self.pose_cov is None or not self.tracked:
            return float("nan"), float("nan")
        c = self.pose_cov
        return float(np.sqrt(np.trace(c[3:, 3:]))), float(np.degrees(np.sqrt(np.trace(c[:3, :3]))))


@dataclass
class _Ref:
    """The reference frame: its pose, keypoints (ideal pixels), descriptors and 3-D points (camera frame, NaN unknown)."""

    T_world_cam: np.ndarray
    uv: np.ndarray
    desc: np.ndarray
    pts_cam: np.ndarray


def _gray(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


class Odometry(Protocol):
    """What the pipeline drives (``FrameToFrameOdometry``, ``vslam.tracking.slam.SlamTracker``): frames in order
    through ``track``; at the end ``finish`` writes what it has beside the trajectory, ``final_poses`` gives the
    frames' poses where the map moved after they were written (None: the online poses stand) and
    ``final_map_ids`` the map each tracked map id ended in after merges, ``recovery_stats`` how often maps were
    started, merged and taken up again. ``metric_scale``: the trajectory is in metres (else it is scored with
    Sim3)."""

    @property
    def metric_scale(self) -> bool: ...

    def track(self, frame: Frame) -> FrameEstimate: ...

    def finish(self, out_dir: object) -> dict: ...

    def final_poses(self, frame_indices: list[int]) -> np.ndarray | None: ...

    def final_map_ids(self, map_ids: list[int]) -> list[int]: ...

    def recovery_stats(self) -> dict[str, int]: ...


class FrameToFrameOdometry:
    """Stateful odometry: feed frames in order with ``track(frame)``."""

    def __init__(self, calib: Calibration, sensor: SensorKind, cfg: OdometryConfig = OdometryConfig()):
        self.calib = calib
        self.sensor = sensor
        self.cfg = cfg
        self.cam: PinholeCamera = calib.cam0
        self.orb = cv2.ORB_create(cfg.n_features)
        self.ref: _Ref | None = None
        self.T_world_cam = np.eye(4)
        self.velocity = np.eye(4)  # T_prev_cur of the last tracked step, for constant-velocity prediction
        self._prev_tracked = False
        self._ref_inliers: int | None = None  # inliers of the first frame measured against the reference
        if sensor == "stereo" and (calib.cam1 is None or calib.T_cam0_cam1 is None):
            raise ValueError("stereo odometry needs cam1 and its extrinsics in the calibration")

    # -- features -------------------------------------------------------
    @property
    def metric_scale(self) -> bool:
        """Monocular odometry chains unit-length steps: its scale is arbitrary (scored with Sim3)."""
        return self.sensor != "mono"

    def _features(self, img: np.ndarray, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> raw pixels (N,2), ideal pixels (N,2), descriptors (N,32) uint8."""
        kps, desc = self.orb.detectAndCompute(_gray(img), None)
        if desc is None or len(kps) == 0:
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        raw = np.array([k.pt for k in kps], dtype=np.float64)
        return raw, cam.undistort_points(raw), desc

    # -- 3-D points of a frame -------------------------------------------
    def _points_rgbd(self, frame: Frame, raw: np.ndarray, uv: np.ndarray) -> np.ndarray:
        pts = np.full((len(raw), 3), np.nan)
        if frame.depth is None or len(raw) == 0:
            return pts
        h, w = frame.depth.shape
        ix = np.clip(np.round(raw).astype(int), 0, [w - 1, h - 1])
        d = frame.depth[ix[:, 1], ix[:, 0]].astype(np.float64)
        ok = (d > self.cfg.min_depth) & (d < self.cfg.max_depth)
        pts[ok] = self.cam.backproject(uv[ok], d[ok])
        return pts

    def _points_stereo(self, frame: Frame, uv: np.ndarray, desc: np.ndarray) -> np.ndarray:
        pts = np.full((len(uv), 3), np.nan)
        if frame.right is None or len(uv) == 0:
            return pts
        cam1 = self.calib.cam1
        assert cam1 is not None
        _, uv_r, desc_r = self._features(frame.right, cam1)
        m = match_mutual(desc, desc_r, ratio=self.cfg.ratio)
        if len(m) == 0:
            return pts
        T_1_0 = inv_T(self.calib.T_cam0_cam1)  # cam0 -> cam1
        P0 = self.cam.K @ np.eye(4)[:3]
        P1 = cam1.K @ T_1_0[:3]
        a, b = uv[m[:, 0]], uv_r[m[:, 1]]
        X = cv2.triangulatePoints(P0, P1, a.T, b.T)
        X = (X[:3] / X[3]).T
        # keep points in front of both cameras, within range, and consistent with both views
        X1 = X @ T_1_0[:3, :3].T + T_1_0[:3, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            err0 = np.linalg.norm(self.cam.project(X) - a, axis=1)
            err1 = np.linalg.norm(cam1.project(X1) - b, axis=1)
        ok = (X[:, 2] > self.cfg.min_depth) & (X[:, 2] < self.cfg.max_depth) & (X1[:, 2] > self.cfg.min_depth)
        ok &= (err0 < self.cfg.stereo_max_epipolar_px) & (err1 < self.cfg.stereo_max_epipolar_px)
        pts[m[ok, 0]] = X[ok]
        return pts

    # -- pose -------------------------------------------------------------
    def _pnp(self, pts_ref: np.ndarray, uv_cur: np.ndarray) -> tuple[np.ndarray | None, int]:
        """T_ref_cur from 3-D points in the reference camera and their pixels in the current one."""
        if len(pts_ref) < max(6, self.cfg.min_inliers):
            return None, 0
        cv2.setRNGSeed(self.cfg.seed)
        guess = inv_T(self.velocity)  # T_cur_ref predicted
        rvec0, _ = cv2.Rodrigues(guess[:3, :3])
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            pts_ref, uv_cur, self.cam.K, None, rvec=rvec0.copy(), tvec=guess[:3, 3].copy().reshape(3, 1),
            useExtrinsicGuess=False, iterationsCount=200, reprojectionError=self.cfg.ransac_px,
            confidence=0.999, flags=cv2.SOLVEPNP_SQPNP,
        )
        if not ok or inl is None or len(inl) < self.cfg.min_inliers:
            return None, 0 if inl is None else len(inl)
        inl = inl.reshape(-1)
        rvec, tvec = cv2.solvePnPRefineLM(pts_ref[inl], uv_cur[inl], self.cam.K, None, rvec, tvec)
        T_cur_ref = make_T(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        return inv_T(T_cur_ref), len(inl)

    def _essential(self, uv_ref: np.ndarray, uv_cur: np.ndarray) -> tuple[np.ndarray | None, int]:
        if len(uv_ref) < max(8, self.cfg.min_inliers):
            return None, 0
        cv2.setRNGSeed(self.cfg.seed)
        E, mask = cv2.findEssentialMat(uv_ref, uv_cur, self.cam.K, cv2.RANSAC, 0.999, self.cfg.ransac_px)
        if E is None or E.shape != (3, 3):
            return None, 0
        n, R, t, mask = cv2.recoverPose(E, uv_ref, uv_cur, self.cam.K, mask=mask)
        if n < self.cfg.min_inliers:
            return None, int(n)
        return inv_T(make_T(R, t.reshape(3))), int(n)  # T_ref_cur with |t| = 1

    def finish(self, out_dir: object) -> dict:
        """Nothing to write besides the per-frame trajectory (no map): the pipeline's common end-of-run hook."""
        return {}

    def final_poses(self, frame_indices: list[int]) -> None:
        """No map to move the poses after they were written: the online poses stand."""
        return None

    def final_map_ids(self, map_ids: list[int]) -> list[int]:
        return list(map_ids)  # one map, never merged

    def recovery_stats(self) -> dict[str, int]:
        return {}  # one map, no recovery beyond the predicted pose

    def track(self, frame: Frame) -> FrameEstimate:
        t0 = time.perf_counter()
        raw, uv, desc = self._features(frame.image, self.cam)
        t1 = time.perf_counter()
        if self.sensor == "rgbd":
            pts = self._points_rgbd(frame, raw, uv)
        elif self.sensor == "stereo":
            pts = self._points_stereo(frame, uv, desc)
        else:
            pts = np.full((len(uv), 3), np.nan)
        t2 = time.perf_counter()
        est = FrameEstimate(self.T_world_cam, tracked=False, n_features=len(uv))
        if self.ref is None:
            est.tracked = len(uv) >= self.cfg.min_inliers
        else:
            m = match_mutual(self.ref.desc, desc, ratio=self.cfg.ratio)
            est.n_matches = len(m)
            if self.sensor == "mono":
                T_ref_cur, est.n_inliers = self._essential(self.ref.uv[m[:, 0]], uv[m[:, 1]])
            else:
                has3d = ~np.isnan(self.ref.pts_cam[m[:, 0], 0]) if len(m) else np.zeros(0, bool)
                mm = m[has3d]
                T_ref_cur, est.n_inliers = self._pnp(self.ref.pts_cam[mm[:, 0]], uv[mm[:, 1]])
            if T_ref_cur is not None:
                T_new = self.ref.T_world_cam @ T_ref_cur
                if self._prev_tracked:  # a gap says nothing reliable about the per-frame motion
                    self.velocity = inv_T(self.T_world_cam) @ T_new
                self.T_world_cam = T_new
                est.tracked = True
                if self._ref_inliers is None:
                    self._ref_inliers = est.n_inliers
            else:
                self.T_world_cam = self.T_world_cam @ self.velocity  # constant-velocity guess
        t3 = time.perf_counter()
        est.T_world_cam = self.T_world_cam.copy()
        self._prev_tracked = est.tracked
        # Keep the reference while it still explains most matches: measuring against one anchor
        # instead of chaining every frame is what keeps a slow or static camera from drifting.
        # A frame without enough 3-D points (no depth) can never become the anchor.
        usable = self.sensor == "mono" or int(np.sum(~np.isnan(pts[:, 0]))) >= self.cfg.min_inliers
        weak = (
            self.sensor == "mono"  # unit-length steps only make sense between consecutive frames
            or self.ref is None
            or self._ref_inliers is None
            or est.n_inliers < self.cfg.keyframe_ratio * self._ref_inliers
        )
        if est.tracked and usable and weak:
            self.ref = _Ref(self.T_world_cam.copy(), uv, desc, pts)
            self._ref_inliers = None
        est.times_ms = {"features": (t1 - t0) * 1e3, "depth": (t2 - t1) * 1e3, "pose": (t3 - t2) * 1e3}
        return est
