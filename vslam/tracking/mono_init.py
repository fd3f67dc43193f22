"""Monocular map initialisation: two views with enough parallax -> two keyframes + points.

The first frame with enough keypoints becomes the reference; every new frame
is matched to it and handed to ``initialize_two_view`` until that accepts (it
needs parallax). If matches to the reference drop too low, the current frame
becomes the new reference. The map's scale is arbitrary (median depth 1 in the
first keyframe) but kept consistent afterwards.

Pair choice (``InitConfig.target_parallax_deg`` > 0): a frame that passes is
taken only once the pair's median parallax reaches the target, or when waiting
would lose the pair (its matches to the reference fell below
``keep_matches_ratio`` of those at the first passing frame, or the tries run
out), and never when its accepted points are fewer than ``min_inlier_ratio`` of
its matches. The pair is always the reference and the current frame: the
tracker goes on from the current frame's pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera, local_bundle_adjustment
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.features.matching import match_mutual
from vslam.geometry.se3 import inv_T
from vslam.mapping.map import KeyFrame, Map
from vslam.tracking.initializer import InitConfig, TwoViewResult, initialize_two_view

log = logging.getLogger(__name__)


@dataclass
class _RefView:
    frame_index: int
    timestamp: float
    features: Features


class MonoInitializer:
    def __init__(self, cam: PinholeCamera, cfg: InitConfig, ratio: float = 0.9, max_tries: int = 30):
        self.cam, self.cfg, self.ratio, self.max_tries = cam, cfg, ratio, max_tries
        self.ref: _RefView | None = None
        self.tries = 0
        self.first_pass_matches = 0  # matches to the reference of the first frame that passed (pair choice)
        self.result: TwoViewResult | None = None  # the two-view geometry of the pair taken (model, parallax)
        self.pair_matches = 0  # matches between the two views of the pair taken

    def try_initialize(self, slam_map: Map, frame_index: int, timestamp: float, feats: Features,
                       stereo_cam: StereoCamera, backend: BackendConfig, run_ba: bool) -> tuple[KeyFrame, KeyFrame] | None:
        """Feed one frame; on success the map holds two keyframes and their points -> (kf0, kf1)."""
        if self.ref is None or self.tries >= self.max_tries:
            self._reset(frame_index, timestamp, feats)
            return None
        self.tries += 1
        m = match_mutual(self.ref.features.desc, feats.desc, ratio=self.ratio)
        if len(m) < self.cfg.min_matches:
            self._reset(frame_index, timestamp, feats)
            return None
        res = initialize_two_view(self.ref.features.uv[m[:, 0]], feats.uv[m[:, 1]], self.cam.K, self.cfg)
        if res is None:
            return None
        good = np.flatnonzero(res.inliers & np.isfinite(res.pts_ref[:, 0]))
        if len(good) < self.cfg.min_points or len(good) < self.cfg.min_inlier_ratio * len(m):
            return None
        if not self._take(res.parallax_deg, len(m)):
            return None
        self.result, self.pair_matches = res, len(m)
        nan = np.full(len(feats), np.nan)
        r = self.ref
        kf0 = slam_map.add_keyframe(r.frame_index, r.timestamp, np.eye(4), r.features, np.full(len(r.features), np.nan),
                                    np.full(len(r.features), np.nan))
        kf1 = slam_map.add_keyframe(frame_index, timestamp, inv_T(res.T_cur_ref), feats, nan.copy(), nan.copy())
        for j in good:
            mp = slam_map.add_point(res.pts_ref[j], kf0.id, int(m[j, 0]))
            slam_map.add_observation(mp.id, kf1.id, int(m[j, 1]))
        if run_ba:
            _two_view_ba(slam_map, kf0, kf1, stereo_cam, backend)
        log.info("monocular map initialised (%s, %.1f deg parallax) between frames %d and %d with %d points",
                 res.model, res.parallax_deg, r.frame_index, frame_index, slam_map.stats()["points"])
        self.ref = None
        return kf0, kf1

    def _take(self, parallax_deg: float, n_matches: int) -> bool:
        """Pair choice: whether a pair that passed every test is taken now or a later frame is waited for."""
        if self.cfg.target_parallax_deg <= 0.0 or parallax_deg >= self.cfg.target_parallax_deg:
            return True
        if self.first_pass_matches == 0:
            self.first_pass_matches = n_matches
        return n_matches < self.cfg.keep_matches_ratio * self.first_pass_matches or self.tries >= self.max_tries - 1

    def _reset(self, frame_index: int, timestamp: float, feats: Features) -> None:
        self.tries = 0
        self.first_pass_matches = 0
        self.ref = _RefView(frame_index, timestamp, feats) if len(feats) >= self.cfg.min_matches else None


def _two_view_ba(slam_map: Map, kf0: KeyFrame, kf1: KeyFrame, stereo_cam: StereoCamera, backend: BackendConfig) -> None:
    """Joint BA of the two initial views (kf0 fixed), drop outliers, then rescale to median depth 1 in kf0."""
    pids = np.array(sorted(slam_map.points), np.int64)
    okf, opt, ouv = [], [], []
    for pid in pids:
        for k, kp in slam_map.points[int(pid)].observations.items():
            okf.append(k), opt.append(int(pid)), ouv.append(slam_map.keyframes[k].features.uv[kp])
    problem = BAProblem({kf0.id: kf0.T_world_cam, kf1.id: kf1.T_world_cam}, {kf0.id},
                        {int(p): slam_map.points[int(p)].xyz for p in pids}, np.array(okf), np.array(opt),
                        np.array(ouv).reshape(-1, 2), np.full(len(okf), np.nan))
    res = local_bundle_adjustment(problem, stereo_cam, backend)
    kf1.T_world_cam = np.asarray(res.poses.get(kf1.id, kf1.T_world_cam), dtype=np.float64)
    for p, X in res.points.items():
        slam_map.points[p].xyz = np.asarray(X, dtype=np.float64)
    slam_map.touch()
    for i in np.flatnonzero(~np.asarray(res.inliers, bool)):
        slam_map.remove_observation(opt[i], okf[i])
    for pid in [p for p, mp in slam_map.points.items() if len(mp.observations) < 2]:
        slam_map.remove_point(pid)
    if not slam_map.points:
        return
    z = np.median(slam_map.points_xyz(np.array(list(slam_map.points)))[:, 2])  # kf0 is the world frame
    if z > 0:
        s = 1.0 / z
        kf1.T_world_cam[:3, 3] *= s
        for mp in slam_map.points.values():
            mp.xyz = mp.xyz * s
        slam_map.touch()
