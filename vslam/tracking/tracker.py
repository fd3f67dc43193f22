"""Tracking: one frame -> its pose against the map, and the keyframe decision.

Per frame (ORB-SLAM's Tracking, single-threaded): project the local map with
the constant-velocity prediction, match by projection, estimate a robust
absolute pose (pycolmap LO-RANSAC with a fixed seed), refine pose-only with the
back end (stereo-like residuals where depth is known), then re-project the
local map with the refined pose for a second, tighter round. When projection
finds too few matches the frame is matched by descriptors against the
reference keyframe (and, after a loss, against the last few keyframes).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from vslam.backend.ba import BackendConfig, StereoCamera, optimize_pose
from vslam.backend.pose_only import pose_covariance
from vslam.data.types import PinholeCamera, SensorKind
from vslam.features.base import Features
from vslam.features.matching import match_by_projection, match_mutual
from vslam.geometry.camera import pnp_setup, project
from vslam.geometry.se3 import inv_T, make_T
from vslam.mapping.map import Map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackingConfig:
    min_depth: float = 0.1  # metres; keypoint depth outside [min, max] is unknown
    max_depth: float = 10.0
    stereo_max_px: float = 1.5  # left-right match must reproject this close in both views
    stereo_refine: bool = True  # rectified rigs: row-guided matching + sub-pixel SAD refinement (features.stereo)
    radius_px: float = 15.0  # projection search radius from the motion prediction, pixels
    radius_lost_px: float = 40.0  # ... right after frames that were not tracked
    radius_refine_px: float = 4.0  # second round, from the refined pose
    # First round (the motion-model PnP) against the previous frame's tracked points only, as ORB-SLAM's
    # TrackWithMotionModel (the whole local map when they give fewer than min_matches, or after a loss), instead
    # of the whole local map. On, it is faster and as good or better on most static scenes, but points on a mover
    # the filter missed were inliers of the previous frame, and from them alone the PnP follows the mover; the
    # whole local map outvotes them. Hence off by default (docs/tracking.md).
    first_round_last_frame: bool = False
    # Motion-model round: when its PnP pose moves the local map's projections (median) farther than the search
    # radius from the prediction's, the prediction failed: the reference keyframe's descriptor matching gives the
    # pose, the projection step's only if it fails (``Tracker.track_projection``). Wide baselines only: with a
    # good prediction it never fires (TUM teddy and KITTI 07 at full rate: the same poses).
    far_prediction_reference: bool = True
    max_hamming: int = 64  # bits (of 256)
    ratio: float = 0.9  # best / second best descriptor distance within the radius
    # A frame this long (seconds) after the last tracked one is a wide baseline (a low frame rate, a dropped
    # stretch): the projection search uses radius_lost_px and keyframe matching the looser ratio_wide, whose
    # extra matches RANSAC sorts out: at 0.5-1 s between frames the 0.8 ratio test leaves too few true matches
    # for PnP (docs/tracking.md, "Never lost").
    wide_gap_s: float = 0.25
    ratio_wide: float = 0.9
    min_matches: int = 30  # fewer projection matches -> descriptor matching against keyframes
    min_inliers: int = 20  # fewer inliers -> the frame is lost (pose predicted, tracked=False)
    ransac_px: float = 3.0
    local_keyframes: int = 20  # reference keyframe + its most covisible ones form the local map
    reloc_keyframes: int = 10  # relocalisation tries the newest N keyframes
    kf_ratio: float = 0.75  # RGB-D/stereo: keyframe when inliers < kf_ratio x tracked points of the reference keyframe
    kf_ratio_mono: float = 0.9  # monocular (ORB-SLAM's thRefRatio values)
    kf_max_frames: int = 30  # ... or this many frames since the last one
    kf_min_frames_mono: int = 3  # monocular: at least this many frames apart (stands in for ORB-SLAM's "mapping busy")
    # ... unless fewer inliers than this are left: under fast acceleration (KITTI 07) the inliers ran out
    # within kf_min_frames_mono frames and tracking was lost (docs/tracking.md).
    kf_min_inliers_mono: int = 60
    kf_close_tracked: int = 100  # RGB-D/stereo: ... or fewer close points tracked than this
    kf_close_untracked: int = 70  # ... while this many close keypoints are not in the map
    # Stereo: the close-point rule at 200. Only about half the keypoints get a stereo depth, so at 100 the
    # rule fired late and keyframes came too far apart. RGB-D at 200 was much slower and not better
    # everywhere, so it stays at 100 there (docs/tracking.md).
    kf_close_tracked_stereo: int = 200
    # RGB-D/stereo: ... or fewer inliers than this. The ratio rule alone waits too long under fast forward
    # motion (synthetic street, 17 cm/frame, few points closer than close_baselines): the fresh points of the
    # reference keyframe are not yet seen by min_obs keyframes, so it never fires and tracking runs dry
    # (docs/tracking.md).
    kf_min_inliers: int = 100
    close_baselines: float = 40.0  # "close" = depth < close_baselines x baseline (ORB-SLAM thDepth)
    min_depth_points: int = 50  # RGB-D/stereo: keypoints with depth needed to start the map / make a keyframe
    seed: int = 0


@dataclass(frozen=True)
class LocalPoints:
    """Map points near the reference keyframe: ids (P,), world positions (P,3), descriptors (P,D)."""

    ids: np.ndarray
    xyz: np.ndarray
    desc: np.ndarray


@dataclass
class TrackResult:
    """Outcome for one frame: T_world_cam (4,4); point_ids (N,) map point per keypoint (inliers only, -1 else)."""

    T_world_cam: np.ndarray
    ok: bool
    point_ids: np.ndarray
    n_matches: int = 0
    n_inliers: int = 0
    method: str = ""
    cov: np.ndarray | None = None  # (6,6) pose covariance of the refinement (``pose_covariance``), None if not measured
    tried_reference: bool = False  # the projection step fell back on the reference keyframe, which failed


def need_keyframe(n_inliers: int, ref_tracked: int, frames_since: int, n_close_tracked: int, n_close_untracked: int,
                  sensor: SensorKind, cfg: TrackingConfig) -> bool:
    """ORB-SLAM's rule (Tracking::NeedNewKeyFrame, local mapping always idle here): insert when
    the tracked points fall below kf_ratio of the reference keyframe's, when RGB-D/stereo runs short of
    close tracked points while many close ones are unmapped, or when kf_max_frames have passed. RGB-D/stereo
    also insert when fewer than kf_min_inliers points are tracked (fast motion, few close points)."""
    close_min = cfg.kf_close_tracked_stereo if sensor == "stereo" else cfg.kf_close_tracked
    close_short = sensor != "mono" and n_close_tracked < close_min and n_close_untracked > cfg.kf_close_untracked
    if sensor == "mono" and frames_since < cfg.kf_min_frames_mono and n_inliers >= cfg.kf_min_inliers_mono:
        return False
    ratio = cfg.kf_ratio_mono if sensor == "mono" else cfg.kf_ratio
    few = sensor != "mono" and n_inliers < cfg.kf_min_inliers
    weak = n_inliers < ratio * ref_tracked or close_short or few
    return bool((weak and n_inliers > 15) or (frames_since >= cfg.kf_max_frames and n_inliers >= cfg.min_inliers))


class Tracker:
    """Pose of a frame against ``slam_map``; holds no state besides the map and cameras."""

    def __init__(self, slam_map: Map, cam: PinholeCamera, stereo_cam: StereoCamera, cfg: TrackingConfig,
                 backend: BackendConfig):
        self.map, self.cam, self.stereo_cam, self.cfg, self.backend = slam_map, cam, stereo_cam, cfg, backend
        self.pycam, self.ao = pnp_setup(cam, cfg.ransac_px, cfg.seed, 30, 1000)
        self._one_round = replace(backend, pose_rounds=1)  # see track_projection
        self._local: tuple[tuple, LocalPoints] | None = None  # the last local map, valid while the map is unchanged

    # -- building blocks ------------------------------------------------------
    def pnp(self, uv: np.ndarray, X: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """RANSAC absolute pose from ideal pixels (M,2) and world points (M,3) -> (T_world_cam | None, inliers (M,))."""
        if len(uv) < max(6, self.cfg.min_inliers):
            return None, np.zeros(len(uv), bool)
        # LO-RANSAC alone, no Ceres refinement after it (most of its time per frame): every caller
        # refines the pose next with the numpy pose-only optimiser (``refine``, ``track_projection``). With no
        # refinement at all before the second round most rows were as good or better but the stereo loop room got
        # worse, hence the round in ``track_projection`` (docs/tracking.md).
        res = pycolmap.estimate_absolute_pose(uv.astype(np.float64), X.astype(np.float64), self.pycam, self.ao)
        if res is None or res["num_inliers"] < self.cfg.min_inliers:
            return None, np.zeros(len(uv), bool)
        M = res["cam_from_world"].matrix()
        return inv_T(make_T(M[:, :3], M[:, 3])), np.asarray(res["inlier_mask"], bool)

    def refine(self, T: np.ndarray, pids: np.ndarray, kps: np.ndarray, ur: np.ndarray, feats: Features,
               X: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Pose-only refinement on matched (point id, keypoint) pairs (X: their positions, if already gathered)
        -> (T_world_cam, inliers (M,))."""
        X = self.map.points_xyz(pids) if X is None else X
        # Unlike BA, pose-only refinement uses one sigma for all levels: per-level sigmas measured worse
        # here (docs/tracking.md), the chi2 gate then lets coarse outliers in.
        return optimize_pose(T, X, feats.uv[kps], ur[kps], self.stereo_cam, self.backend)

    def search_local(self, T: np.ndarray, local: LocalPoints, feats: Features, tree: cKDTree, radius: float,
                     seen: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Projection matching of the local map -> (indices into ``local`` of the matched points, keypoint
        indices, visible mask over ``local``). ``seen``: (uv, visible) of ``project(T, local.xyz)`` if computed."""
        uv, vis = seen if seen is not None else self._project(T, local.xyz)
        idx = np.flatnonzero(vis)
        if len(idx) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), vis
        pairs = match_by_projection(uv[idx], local.desc[idx], feats.uv, feats.desc, radius, self.cfg.max_hamming,
                                    self.cfg.ratio, tree)
        return idx[pairs[:, 0]], pairs[:, 1], vis

    def local_points(self, ref_kf: int) -> LocalPoints:
        """The local map of ``ref_kf`` (it and its most covisible keyframes) with positions and descriptors,
        gathered for both matching rounds, and again only when the reference or the map (``Map.revision``) has
        changed: between keyframes it is the same for every frame."""
        key = (self.map, self.map.revision, ref_kf)
        if self._local is not None and self._local[0] == key:
            return self._local[1]
        _, pids = self.map.local_map(ref_kf, self.cfg.local_keyframes)
        local = self._gather(pids)
        self._local = (key, local)
        return local

    def _moved_px(self, T_a: np.ndarray, T_b: np.ndarray, xyz: np.ndarray,
                  seen_a: tuple[np.ndarray, np.ndarray] | None = None) -> float:
        """Median image displacement (px) of the points ``xyz`` (P,3) visible from both poses, from ``T_a`` to
        ``T_b``; 0 when none is. ``seen_a``: (uv, visible) of ``project(T_a, xyz)`` when already computed."""
        uv_a, vis_a = seen_a if seen_a is not None else self._project(T_a, xyz)
        uv_b, vis_b = self._project(T_b, xyz)
        both = vis_a & vis_b
        return float(np.median(np.linalg.norm(uv_b[both] - uv_a[both], axis=1))) if both.any() else 0.0

    def _project(self, T_world_cam: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``project`` -> (uv (P,2), visible (P,))."""
        uv, _, vis = project(T_world_cam, xyz, self.cam, self.cfg.min_depth)
        return uv, vis

    def _gather(self, ids: np.ndarray) -> LocalPoints:
        return LocalPoints(ids, self.map.points_xyz(ids), self.map.descriptors(ids))

    def _result(self, T: np.ndarray, pids: np.ndarray, kps: np.ndarray, inl: np.ndarray, n: int, method: str, n_matches: int) -> TrackResult:
        point_ids = np.full(n, -1, np.int64)
        point_ids[kps[inl]] = pids[inl]
        ok = int(inl.sum()) >= self.cfg.min_inliers
        return TrackResult(T, ok, point_ids, n_matches, int(inl.sum()), method)

    def finish_local(self, T: np.ndarray, feats: Features, ur: np.ndarray, ref_kf: int, tree: cKDTree, method: str,
                     local: LocalPoints | None = None) -> TrackResult:
        """Second round: the whole local map (``local``, else that of ``ref_kf``) from a good pose, tight radius,
        pose-only refinement."""
        if local is None:
            local = self.local_points(ref_kf)
        sel, mk, vis = self.search_local(T, local, feats, tree, self.cfg.radius_refine_px)
        mp, X = local.ids[sel], local.xyz[sel]
        if len(mp) < self.cfg.min_inliers:
            return TrackResult(T, False, np.full(len(feats), -1, np.int64), len(mp), 0, method)
        T2, inl = self.refine(T, mp, mk, ur, feats, X)
        points = self.map.points
        for pid in local.ids[vis].tolist():  # Python ints: faster dict lookups than numpy scalars
            points[pid].n_visible += 1
        for pid in mp[inl].tolist():
            points[pid].n_found += 1
        res = self._result(T2, mp, mk, inl, len(feats), method, len(mp))
        if res.ok:  # every measured pose says how uncertain it is (cheap: docs/tracking.md)
            res.cov = pose_covariance(T2, X[inl], feats.uv[mk[inl]], ur[mk[inl]], self.stereo_cam, self.backend)
        return res

    # -- strategies -----------------------------------------------------------
    def track_projection(self, feats: Features, ur: np.ndarray, T_pred: np.ndarray, ref_kf: int, radius: float, tree: cKDTree,
                         last_ids: np.ndarray | None = None, ratio: float = 0.8) -> TrackResult | None:
        """Motion-model round (``last_ids``: the previous frame's tracked points, else / if too few: the local
        map) + LO-RANSAC PnP, then ``finish_local``."""
        local = self.local_points(ref_kf)
        sel = np.zeros(0, np.int64)
        seen = None  # the local map's projection from T_pred, once computed (``_moved_px`` needs it again)
        if last_ids is not None and len(last_ids) >= self.cfg.min_matches:
            ids = self.map.existing(last_ids)  # loop fusion may have merged some
            if len(ids) >= self.cfg.min_matches:
                last = self._gather(ids)
                sel, mk, _ = self.search_local(T_pred, last, feats, tree, radius)
                X = last.xyz[sel]
        if len(sel) < self.cfg.min_matches:
            seen = self._project(T_pred, local.xyz)
            sel, mk, _ = self.search_local(T_pred, local, feats, tree, radius, seen)
            X = local.xyz[sel]
        if len(sel) < self.cfg.min_matches:
            return None
        T, inl = self.pnp(feats.uv[mk], X)
        if T is None:
            return None
        far = self.cfg.far_prediction_reference and self._moved_px(T_pred, T, local.xyz, seen) > radius
        if far:
            # The pose moved the local map farther than the search radius from where the prediction put it: the
            # true matches of most points lay outside their windows, and those found are where the prediction
            # happened to be close (one image region, one depth), a subset that may pin the pose badly and that the
            # tight second round cannot leave (seen on TUM teddy: docs/tracking.md). The reference keyframe's
            # descriptor matches do not depend on the prediction.
            ref = self.track_keyframe(feats, ur, ref_kf, tree, ratio=ratio)
            if ref is not None and ref.ok:
                return ref
        # One cheap least-squares round on the RANSAC inliers before the tight second-round search: the
        # LO-RANSAC pose alone cost the stereo loop room accuracy that this round gives back as well as pycolmap's
        # Ceres refinement did, for a fraction of its time (docs/tracking.md).
        T, _ = optimize_pose(T, X[inl], feats.uv[mk[inl]], ur[mk[inl]], self.stereo_cam, self._one_round)
        res = self.finish_local(T, feats, ur, ref_kf, tree, "projection", local)  # the map has not changed since
        res.tried_reference = far
        return res

    def track_keyframe(self, feats: Features, ur: np.ndarray, kf_id: int, tree: cKDTree, method: str = "reference",
                       ratio: float = 0.8) -> TrackResult | None:
        """Descriptor matching against one keyframe's map points (mutual, ``ratio`` test), PnP, then the local-map
        round."""
        kf = self.map.keyframes[kf_id]
        kps_kf = np.flatnonzero(kf.point_ids >= 0)
        if len(kps_kf) < self.cfg.min_inliers:
            return None
        m = match_mutual(kf.features.desc[kps_kf], feats.desc, ratio=ratio, max_dist=self.cfg.max_hamming)
        if len(m) < self.cfg.min_inliers:
            return None
        pids, kps = kf.point_ids[kps_kf[m[:, 0]]], m[:, 1]
        T, inl = self.pnp(feats.uv[kps], self.map.points_xyz(pids))
        if T is None:
            return None
        T_ref, inl = self.refine(T, pids[inl], kps[inl], ur, feats)
        # Few descriptor matches survive a wide baseline (frames 0.1-0.2 m, 7-15 deg apart), and the refinement's
        # depth residuals drop more of them; the local-map round from the RANSAC pose, not this count, decides.
        return self.finish_local(T_ref if inl.sum() >= self.cfg.min_inliers else T, feats, ur, kf_id, tree, method)

    def track(self, feats: Features, ur: np.ndarray, T_pred: np.ndarray, ref_kf: int, after_loss: bool,
              last_ids: np.ndarray | None = None, wide: bool = False) -> TrackResult:
        """Try projection, then the reference keyframe, then (after a loss) the newest keyframes. ``last_ids``:
        map points tracked in the previous frame (``TrackingConfig.first_round_last_frame``); ``wide``: the frame
        comes ``wide_gap_s`` or more after the last tracked one (wider search, looser ratio test)."""
        fail = TrackResult(T_pred, False, np.full(len(feats), -1, np.int64))
        if len(feats) < self.cfg.min_inliers:
            return fail
        tree = cKDTree(feats.uv)
        radius = self.cfg.radius_lost_px if after_loss or wide else self.cfg.radius_px
        ratio = self.cfg.ratio_wide if wide else 0.8
        use_last = self.cfg.first_round_last_frame and not after_loss
        res = self.track_projection(feats, ur, T_pred, ref_kf, radius, tree, last_ids if use_last else None, ratio)
        if res is None or (not res.ok and not res.tried_reference):
            res = self.track_keyframe(feats, ur, ref_kf, tree, ratio=ratio)
        if (res is None or not res.ok) and (after_loss or wide):
            for kf_id in sorted(self.map.keyframes, reverse=True)[: self.cfg.reloc_keyframes]:
                if kf_id != ref_kf:
                    res = self.track_keyframe(feats, ur, kf_id, tree, "relocalised", ratio)
                    if res is not None and res.ok:
                        break
        return res if res is not None and res.ok else fail

    def best_reference(self, point_ids: np.ndarray, default: int) -> int:
        """The keyframe observing most of the frame's tracked points (ties: newest)."""
        counts: dict[int, int] = {}
        points = self.map.points
        for pid in point_ids[point_ids >= 0].tolist():
            for k in points[pid].observations:
                counts[k] = counts.get(k, 0) + 1
        if not counts:
            return default
        return max(counts.items(), key=lambda kv: (kv[1], kv[0]))[0]
