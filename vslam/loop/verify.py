"""Geometric verification of a loop candidate: does the query keyframe see the candidate's map?

ORB-SLAM verifies with a Sim3 from keyframe-to-keyframe matches; with depth
(RGB-D/stereo) the scale is known, so we solve the query's absolute pose in the
*old* map directly: descriptor matches from the query keypoints to the map
points of the candidate and its covisible keyframes, LO-RANSAC PnP (pycolmap,
fixed seed), robust pose-only refinement with the stereo-like residuals, then
a guided projection search over the same points and a second refinement. A
candidate that only looks similar (repeated texture, the same object class)
fails the inlier count; the verified pose is the loop measurement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from vslam.backend.ba import BackendConfig, StereoCamera, optimize_pose
from vslam.backend.pose_only import pose_covariance
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.features.matching import match_by_projection, match_mutual
from vslam.geometry.se3 import inv_T, make_T
from vslam.loop.config import LoopConfig
from vslam.mapping.map import Map
from vslam.geometry.camera import pnp_setup, project


@dataclass
class LoopMatch:
    """A verified loop: T_world_cam (4,4) of the query in the old map's frame; point_ids (N,) per query
    keypoint the matched inlier map point (-1 none); candidate: the old keyframe id."""

    candidate: int
    T_world_cam: np.ndarray
    point_ids: np.ndarray
    n_matches: int
    n_inliers: int
    std_m: float = float("nan")  # first-order position std of T_world_cam (map points taken as exact), metres


class LoopVerifier:
    """Holds the pycolmap camera and RANSAC options; ``verify`` is pure given the map."""

    def __init__(self, cam: PinholeCamera, stereo_cam: StereoCamera, cfg: LoopConfig, backend: BackendConfig):
        self.cam, self.stereo_cam, self.cfg, self.backend = cam, stereo_cam, cfg, backend
        self.pycam, self.ao = pnp_setup(cam, cfg.ransac_px, cfg.seed, 100, 2000)

    def candidate_points(self, m: Map, candidate: int, max_kf: int | None = None) -> np.ndarray:
        """Map point ids seen by the candidate and its most covisible keyframes with id <= ``max_kf``
        (sorted, unique). ``max_kf`` keeps the recent, drifted keyframes out: a loop candidate already
        covisible with them would otherwise mix old and drifted points in one PnP (seen on the loop room:
        a wrong loop measurement; docs/loop.md, "Verification")."""
        kfs = [candidate] + [k for k in m.covisible_keyframes(candidate, 15) if max_kf is None or k <= max_kf]
        kfs = kfs[: self.cfg.local_keyframes]
        ids = np.unique(np.concatenate([m.keyframes[k].point_ids for k in kfs]))
        ids = ids[ids >= 0]
        if max_kf is None:
            return ids
        return np.array([p for p in ids if max(m.points[int(p)].observations) <= max_kf], np.int64)

    def verify(self, m: Map, feats: Features, ur: np.ndarray, candidate: int, exclude_points: np.ndarray | None = None,
               max_kf: int | None = None) -> LoopMatch | None:
        """Query keypoints ``feats`` (+ their virtual right x ``ur``, NaN mono) against ``candidate``'s local map.

        exclude_points: map point ids never used (the query's own points, so a loop is not "verified" on
        points that tracking already shares); max_kf: only points seen by no keyframe newer than this.
        -> LoopMatch or None when rejected.
        """
        cfg = self.cfg
        pids = self.candidate_points(m, candidate, max_kf)
        if exclude_points is not None and len(exclude_points):
            pids = np.setdiff1d(pids, exclude_points)
        if len(pids) < cfg.min_matches or len(feats) < cfg.min_matches:
            return None
        pair = match_mutual(m.descriptors(pids), feats.desc, ratio=cfg.ratio, max_dist=cfg.max_hamming)
        if len(pair) < cfg.min_matches:
            return None
        mp, kp = pids[pair[:, 0]], pair[:, 1]
        res = pycolmap.estimate_and_refine_absolute_pose(feats.uv[kp].astype(np.float64), m.points_xyz(mp), self.pycam, self.ao)
        if res is None or res["num_inliers"] < cfg.min_pnp_inliers:
            return None
        M = res["cam_from_world"].matrix()
        T = inv_T(make_T(M[:, :3], M[:, 3]))
        inl = np.asarray(res["inlier_mask"], bool)
        T, inl2 = optimize_pose(T, m.points_xyz(mp[inl]), feats.uv[kp[inl]], ur[kp[inl]], self.stereo_cam, self.backend)
        if int(inl2.sum()) < cfg.min_pnp_inliers:
            return None
        # guided search over the whole candidate map from the verified pose, then refine again
        uv, _, vis = project(T, m.points_xyz(pids), self.cam)
        idx = np.flatnonzero(vis)
        g = match_by_projection(uv[idx], m.descriptors(pids[idx]), feats.uv, feats.desc, cfg.guided_radius_px,
                                cfg.max_hamming, 0.9)
        if len(g) < cfg.min_inliers:
            return None
        gp, gk = pids[idx[g[:, 0]]], g[:, 1]
        T, inl3 = optimize_pose(T, m.points_xyz(gp), feats.uv[gk], ur[gk], self.stereo_cam, self.backend)
        n_in = int(inl3.sum())
        if n_in < cfg.min_inliers:
            return None
        # A loop seen over a narrow overlap (far points on one side of the image) fits a wrong pose almost as
        # well as the true one, with many inliers but a larger predicted std (docs/loop.md, "Verification").
        # The loop edge would bend the whole map, so such loops wait for a better view of the same place.
        cov = pose_covariance(T, m.points_xyz(gp[inl3]), feats.uv[gk[inl3]], ur[gk[inl3]], self.stereo_cam, self.backend)
        std_m = float(np.sqrt(np.trace(cov[3:, 3:])))
        if not std_m <= cfg.max_std_m:
            return None
        point_ids = np.full(len(feats), -1, np.int64)
        point_ids[gk[inl3]] = gp[inl3]
        return LoopMatch(candidate, T, point_ids, len(g), n_in, std_m)
