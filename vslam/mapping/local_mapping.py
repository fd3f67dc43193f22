"""Local mapping, run right after each new keyframe (ORB-SLAM's LocalMapping); its local BA either at once or
in a worker process while tracking goes on (``MappingConfig.ba_lag_frames``).

Steps: attach the tracked observations, create new points (RGB-D/stereo:
back-project keypoints with depth; monocular: triangulate unmatched keypoint
pairs with covisible keyframes), fuse duplicates with the neighbours, cull
weak recent points, then local bundle adjustment over the most covisible
keyframes with the others that see those points held fixed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera, local_bundle_adjustment
from vslam.backend.factors import FactorCache
from vslam.backend.worker import BAWorker
from vslam.data.types import PinholeCamera, SensorKind
from vslam.features.matching import match_by_projection, match_epipolar, match_mutual
from vslam.geometry.se3 import inv_T
from vslam.geometry.triangulation import fundamental, triangulate_points
from vslam.mapping.map import KeyFrame, Map
from vslam.geometry.camera import project

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MappingConfig:
    ba_window: int = 8  # keyframes optimised by local BA (the new one + its most covisible)
    ba_max_fixed: int = 16  # at most this many fixed keyframes (most observations first)
    ba: bool = True
    min_shared: int = 15  # covisibility edge: keyframes sharing at least this many points
    cull_found_ratio: float = 0.25  # recent point found/visible below this -> removed
    cull_min_obs_mono: int = 2  # recent point seen by fewer keyframes after cull_age -> removed
    # RGB-D/stereo: ORB-SLAM2's rule is Observations() <= 3 with a stereo observation counting twice, i.e. a
    # point seen by 2 keyframes survives; 3 keyframes starved fast or relit sequences of points, and 2 was
    # better on every row tried (docs/tracking.md, "Local mapping").
    cull_min_obs_depth: int = 2
    cull_age: int = 2  # keyframes after creation when the observation count is checked
    fuse_neighbors: int = 6  # fuse new points into this many covisible keyframes (and back)
    fuse_radius_px: float = 3.0
    max_hamming: int = 50
    triangulate: Literal["mono", "all", "none"] = "mono"  # which sensors create points by two-view triangulation
    tri_neighbors: int = 5
    # Points triangulated with less parallax carry a depth too uncertain to hold a monocular scale; more
    # parallax starves the map (KITTI 07 mono sweep: docs/tracking.md, "Local mapping").
    tri_parallax_deg: float = 1.5
    tri_max_reproj_px: float = 2.0
    # How new points find their second view. "epipolar" (ORB-SLAM's SearchForTriangulation): candidates within
    # sqrt(tri_epipolar_chi2) x 1.2^octave px of the epipolar line, away from the epipole, best Hamming <
    # tri_ratio x second best; "mutual": global mutual nearest neighbours with a 0.75 ratio test (repetitive
    # texture fails it, so fewer points are made). Epipolar was the more accurate on KITTI 07 mono
    # (docs/tracking.md, "Local mapping").
    tri_matching: Literal["epipolar", "mutual"] = "epipolar"
    tri_epipolar_chi2: float = 3.84
    tri_ratio: float = 0.7
    max_new_points: int = 1000  # RGB-D/stereo points created per keyframe, closest first
    level_sigma: bool = False  # BA pixel sigma grows with the keypoint's pyramid level (scale^level)
    # Local BA needs the window tied to the fixed keyframes by enough shared points, else it floats on a few
    # (seen on the synthetic loop room, RGB-D). Below this count the oldest window keyframes are held fixed
    # too, the new keyframe always stays free. 30 fixes the floating window without costing the plain room
    # (sweep: docs/tracking.md, "Local mapping").
    ba_min_anchor_points: int = 30
    # Local BA in a second process (``vslam.backend.worker``) while tracking goes on, ORB-SLAM's LocalMapping
    # thread on a fixed schedule: the result is written back ``ba_lag_frames`` frames after its keyframe, or
    # when the next keyframe is wanted if that comes first (the keyframe decision is then taken again on the
    # adjusted map), so the same input still gives the same trajectory. The frames in between track against
    # the map as it was. 0 = solve at once, in this process: a lag cost accuracy everywhere (stereo points
    # need their BA before they are tracked; monocular KITTI is lost at long lags) and, since the front end
    # runs on the second core (``RuntimeConfig.frontend_thread``), no longer saves time (bench rows ``*-async``;
    # docs/tracking.md, "BA lag").
    ba_lag_frames: int = 0
    # Monocular: while the map holds at most this many keyframes, local BA adjusts all of them (the first held
    # fixed), so the first map's scale is fitted over every early keyframe, not the newest window alone. 0 = off.
    full_ba_keyframes: int = 0


class GatheredPoints:
    """Positions and descriptors of map points ``ids`` read once for a fusion pass over several keyframes:
    fusing changes neither (a merge keeps the kept point's), only which ids still exist and who sees them."""

    def __init__(self, slam_map: Map, ids: np.ndarray):
        self.ids = np.unique(np.asarray(ids, np.int64))
        self.xyz = slam_map.points_xyz(self.ids)
        self.desc = slam_map.descriptors(self.ids)

    def rows(self, pids: np.ndarray) -> np.ndarray:
        """Rows of ``pids`` (each one of ``ids``)."""
        return np.searchsorted(self.ids, pids)


class LocalMapper:
    """Owns nothing but the map reference and settings; ``process(kf)`` mutates the map."""

    def __init__(self, slam_map: Map, cam: PinholeCamera, stereo_cam: StereoCamera, sensor: SensorKind,
                 cfg: MappingConfig, backend: BackendConfig):
        self.map, self.cam, self.stereo_cam, self.sensor, self.cfg, self.backend = slam_map, cam, stereo_cam, sensor, cfg, backend
        self.recent: list[int] = []  # point ids still on probation (culling)
        # visual-inertial mode (``vslam.tracking.vio.Vio``): adds its IMU chain to the BA window and solves it
        self.inertial = None
        # line landmarks (``vslam.mapping.line_map.LineSlam``) join local BA when set
        self.lines = None
        self.worker: BAWorker | None = None  # ba_lag_frames > 0: the process that solves local BA
        if cfg.ba and cfg.ba_lag_frames > 0:
            self.worker = BAWorker()
            self.worker.start()
        self.pending = None  # (problem, obs keyframes, obs points, fixed) of the worker's BA not yet written back
        self.factor_cache = FactorCache()  # local BA's factors of the last window, reused by the next

    def process(self, kf: KeyFrame, tracked_ids: np.ndarray) -> dict[str, float]:
        """Insert keyframe ``kf`` whose keypoints matched ``tracked_ids`` (N,) (-1 none). -> ms per step."""
        ms: dict[str, float] = {}
        t = time.perf_counter()
        kps = np.flatnonzero(tracked_ids >= 0)
        points = self.map.points
        for kp, pid in zip(kps.tolist(), tracked_ids[kps].tolist()):  # Python ints: cheaper dict lookups
            if pid in points:
                self.map.add_observation(pid, kf.id, kp)
        neighbors = self.map.covisible_keyframes(kf.id, 1, max(self.cfg.fuse_neighbors, self.cfg.tri_neighbors))
        new = self.create_depth_points(kf) if self.sensor != "mono" else []
        if self.cfg.triangulate == "all" or (self.cfg.triangulate == "mono" and self.sensor == "mono"):
            new += self.triangulate(kf, neighbors[: self.cfg.tri_neighbors])
        if self.lines is not None:
            self.lines.triangulate(kf, neighbors[: self.cfg.tri_neighbors])
        self.recent.extend(new)
        ms["create"] = (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        self.fuse(kf, neighbors[: self.cfg.fuse_neighbors])
        self.map.update_descriptors(np.unique(kf.point_ids[kf.point_ids >= 0]))
        self.cull(kf.id)
        ms["fuse_cull"] = (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        if self.cfg.ba and len(self.map.keyframes) >= 2:
            self.bundle_adjust(kf.id, in_worker=self.cfg.ba_lag_frames > 0)
        ms["ba"] = (time.perf_counter() - t) * 1e3
        return ms

    # -- point creation --------------------------------------------------------
    def create_depth_points(self, kf: KeyFrame) -> list[int]:
        """Back-project keypoints with depth that are not yet map points (closest first, at most max_new_points)."""
        free = np.flatnonzero((kf.point_ids < 0) & np.isfinite(kf.depth))
        free = free[np.argsort(kf.depth[free], kind="stable")][: self.cfg.max_new_points]
        if len(free) == 0:
            return []
        Xc = self.cam.backproject(kf.features.uv[free], kf.depth[free])
        Xw = Xc @ kf.T_world_cam[:3, :3].T + kf.T_world_cam[:3, 3]
        return self.map.add_points(Xw, kf.id, free)

    def triangulate(self, kf: KeyFrame, neighbors: list[int]) -> list[int]:
        """New points from descriptor matches of unmatched keypoints between ``kf`` and each neighbour."""
        new: list[int] = []
        for nb_id in neighbors:
            nb = self.map.keyframes[nb_id]
            a = np.flatnonzero(kf.point_ids < 0)
            b = np.flatnonzero(nb.point_ids < 0)
            if len(a) < 8 or len(b) < 8:
                continue
            m = self._tri_matches(kf, nb, a, b)
            if len(m) == 0:
                continue
            ia, ib = a[m[:, 0]], b[m[:, 1]]
            X, ok = triangulate_points(kf.T_world_cam, nb.T_world_cam, kf.features.uv[ia], nb.features.uv[ib], self.cam.K,
                                       self.cfg.tri_parallax_deg, self.cfg.tri_max_reproj_px)
            if ok.any():
                # ia / ib are distinct free keypoints of kf / nb: the batch calls make what add_point and
                # add_observation per pair would (same ids, observations in the same order)
                ids = self.map.add_points(X[ok], kf.id, ia[ok])
                self.map.add_free_observations(ids, nb_id, ib[ok])
                new += ids
        return new

    def _tri_matches(self, kf: KeyFrame, nb: KeyFrame, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(M,2) pairs of positions in ``a`` (kf's unmatched keypoints) and ``b`` (nb's), see ``tri_matching``."""
        da, db = kf.features.desc[a], nb.features.desc[b]
        if self.cfg.tri_matching == "mutual":
            return match_mutual(da, db, ratio=0.75, max_dist=self.cfg.max_hamming)
        t = (inv_T(nb.T_world_cam) @ kf.T_world_cam)[:3, 3]
        F = fundamental(kf.T_world_cam, nb.T_world_cam, self.cam.K)
        scale = nb.features.scale_factor ** nb.features.octave[b].astype(np.float64)
        epipole = None
        if abs(t[2]) > 1e-9:  # a's centre seen from b (ORB-SLAM: skip keypoints within 10 sqrt(scale) px)
            epipole = (self.cam.K @ t)[:2] / t[2]
        return match_epipolar(kf.features.uv[a], da, nb.features.uv[b], db, F,
                              np.sqrt(self.cfg.tri_epipolar_chi2) * scale, epipole, 10.0 * np.sqrt(scale),
                              max_dist=self.cfg.max_hamming, ratio=self.cfg.tri_ratio)

    # -- fusion and culling ----------------------------------------------------
    def _fuse_into(self, target: KeyFrame, pids: np.ndarray, gathered: GatheredPoints | None = None) -> int:
        """Project ``pids`` into ``target``; attach to free keypoints, merge with duplicates. -> fusions.
        Ids no longer in the map are skipped (loop fusion passes one list to several keyframes, merging as it goes).
        ``gathered``: the points' positions and descriptors, read once for several calls (else read here)."""
        seen, points = set(target.point_ids.tolist()), self.map.points
        # still in the map and not already seen by the target, in order (one pass over Python ints)
        pids = np.array([p for p in np.asarray(pids, np.int64).tolist() if p not in seen and p in points], np.int64)
        if len(pids) == 0 or len(target.features) == 0:
            return 0
        g = gathered if gathered is not None else GatheredPoints(self.map, pids)
        rows = g.rows(pids)
        uv, z, vis = project(target.T_world_cam, g.xyz[rows], self.cam)
        idx = np.flatnonzero(vis)
        if len(idx) == 0:
            return 0
        pairs = match_by_projection(uv[idx], g.desc[rows[idx]], target.features.uv, target.features.desc,
                                    self.cfg.fuse_radius_px, self.cfg.max_hamming, 1.0)
        if len(pairs) == 0:
            return 0
        zk = target.depth[pairs[:, 1]]
        with np.errstate(invalid="ignore"):
            clash = np.isfinite(zk) & (np.abs(zk - z[idx[pairs[:, 0]]]) > 0.1 * zk)  # depth disagrees: a different surface
        pairs = pairs[~clash]
        tid, n = target.id, 0
        # in pair order: each fusion changes what the next one sees (merges remove points)
        for pid, kp in zip(pids[idx[pairs[:, 0]]].tolist(), pairs[:, 1].tolist()):
            mp = points.get(pid)
            if mp is None or tid in mp.observations:
                continue
            old = int(target.point_ids[kp])
            if old < 0:
                self.map.add_observation(pid, tid, kp)
            else:
                keep, drop = (old, pid) if len(points[old].observations) >= len(mp.observations) else (pid, old)
                self.map.merge_points(keep, drop)
            n += 1
        return n

    def fuse(self, kf: KeyFrame, neighbors: list[int]) -> None:
        ids = np.concatenate([kf.point_ids] + [self.map.keyframes[n].point_ids for n in neighbors])
        gathered = GatheredPoints(self.map, ids[ids >= 0])  # every id the passes below can see
        mine = kf.point_ids[kf.point_ids >= 0]
        for nb_id in neighbors:
            self._fuse_into(self.map.keyframes[nb_id], mine, gathered)
            mine = kf.point_ids[kf.point_ids >= 0]
        theirs = [self.map.keyframes[n].point_ids for n in neighbors]
        if theirs:
            cand = np.unique(np.concatenate(theirs))
            self._fuse_into(kf, cand[cand >= 0], gathered)

    def cull(self, cur_kf: int) -> None:
        """ORB-SLAM MapPointCulling on points created in the last few keyframes."""
        min_obs = self.cfg.cull_min_obs_mono if self.sensor == "mono" else self.cfg.cull_min_obs_depth
        keep: list[int] = []
        points, remove = self.map.points, self.map.remove_point
        min_ratio, cull_age = self.cfg.cull_found_ratio, self.cfg.cull_age
        for pid in self.recent:  # thousands of points per RGB-D keyframe: attribute lookups hoisted
            mp = points.get(pid)
            if mp is None:
                continue
            age = cur_kf - mp.first_kf
            if mp.found_ratio < min_ratio or (age >= cull_age and len(mp.observations) < min_obs):
                remove(pid)
            elif age < cull_age + 1:
                keep.append(pid)
        self.recent = keep

    # -- local bundle adjustment -----------------------------------------------
    def _anchor_window(self, kf_id: int, window: list[int], fixed: list[int], pts: np.ndarray) -> None:
        """Move the oldest window keyframes (never ``kf_id``) into ``fixed`` (in place) until the fixed
        keyframes observe at least ``ba_min_anchor_points`` of the window points ``pts``."""
        fixed_set = set(fixed)
        observations = [self.map.points[p].observations for p in pts.tolist()]

        def n_anchored() -> int:
            return len(observations) - sum(map(fixed_set.isdisjoint, observations))

        while n_anchored() < self.cfg.ba_min_anchor_points:
            older = sorted(k for k in window if k != kf_id)
            if not older:
                return
            window.remove(older[0])
            fixed.append(older[0])
            fixed_set.add(older[0])

    def bundle_adjust(self, kf_id: int, in_worker: bool = False) -> None:
        """Local BA around ``kf_id``, solved here and written back now, or (``in_worker``) handed to the worker
        process and left in ``pending`` until ``flush``. Visual-inertial windows are always solved here."""
        job = self._ba_job(kf_id)
        if job is None:
            return
        problem, okf, opt, fixed, chain = job
        if len(chain) >= 2:
            res = self.inertial.solve(problem, self.stereo_cam, self.backend)
        elif in_worker:
            if self.worker is None:
                self.worker = BAWorker()
            self.worker.submit(problem, self.stereo_cam, self.backend)
            self.pending = (problem, okf, opt, fixed)
            return
        else:
            res = local_bundle_adjustment(problem, self.stereo_cam, self.backend, cache=self.factor_cache)
        self._apply_ba(problem, res, okf, opt, fixed)

    def flush(self) -> float:
        """Wait for the pending worker BA (if any) and write it back. -> ms spent waiting for the worker."""
        if self.pending is None:
            return 0.0
        problem, okf, opt, fixed = self.pending
        self.pending = None
        t = time.perf_counter()
        res = self.worker.result()  # type: ignore[union-attr]
        ms = (time.perf_counter() - t) * 1e3
        self._apply_ba(problem, res, okf, opt, fixed)
        return ms

    def close(self) -> None:
        """Stop the worker process (a pending result is dropped: call ``flush`` first to keep it)."""
        self.pending = None
        if self.worker is not None:
            self.worker.close()
            self.worker = None

    def _ba_job(self, kf_id: int):
        """-> (BAProblem, observation keyframe ids, point ids, fixed keyframes, IMU chain) or None (nothing to do)."""
        m = self.map
        if self.sensor == "mono" and len(m.keyframes) <= self.cfg.full_ba_keyframes:
            window = [kf_id] + sorted(k for k in m.keyframes if k != kf_id)
        else:
            window = [kf_id] + m.covisible_keyframes(kf_id, self.cfg.min_shared, self.cfg.ba_window - 1)
        chain = self.inertial.chain() if self.inertial is not None else []
        window += [k for k in chain if k not in window]  # IMU-linked keyframes are optimised too
        pts = np.unique(np.concatenate([m.keyframes[k].point_ids for k in window]))
        pts = pts[pts >= 0]
        if len(pts) == 0:
            return None
        points = m.points
        fixed_counts = m.observers(pts)  # the window's own keyframes dropped below
        for k in window:
            fixed_counts.pop(k, None)
        fixed = sorted(fixed_counts, key=lambda k: (-fixed_counts[k], k))[: self.cfg.ba_max_fixed]
        first = min(m.keyframes)
        if first in window:  # the first keyframe anchors the gauge (and, monocular, helps hold the scale)
            window.remove(first)
            fixed.append(first)
        if not fixed:
            fixed = [window.pop()]
        self._anchor_window(kf_id, window, fixed, pts)
        if not window:
            return None
        free = set(window)
        links = [ln for ln in m.links if ln.a in free or ln.b in free]  # dense-step relative poses (PoseLink)
        fixed += sorted({k for ln in links for k in (ln.a, ln.b)} - free - set(fixed))
        allk = sorted(set(window) | set(fixed))
        # every observation of a window point in a window or fixed keyframe, read from the keyframes' point
        # arrays (the map keeps them equal to the points' observations), ordered by point, then keyframe
        cols: list[tuple] = []
        member = np.zeros(int(pts[-1]) + 2, bool)  # by point id; the last slot (no window point) takes -1 and beyond
        member[pts] = True
        last = member.size - 1
        for k in allk:
            kf = m.keyframes[k]
            kp = np.flatnonzero(member[np.where(kf.point_ids < 0, last, np.minimum(kf.point_ids, last))])
            cols.append((np.full(kp.size, k, np.int64), kf.point_ids[kp], kf.features.uv[kp], kf.ur[kp],
                         kf.features.scale_factor ** kf.features.octave[kp].astype(np.float64)))
        okf, opt, ouv, our, osg = (np.concatenate(c) for c in zip(*cols))
        order = np.lexsort((okf, opt))
        okf, opt, ouv, our, osg = okf[order], opt[order], ouv[order], our[order], osg[order]
        # ORB-SLAM weights a keypoint of pyramid level l by sigma = scale^l. Measured here it did not pay
        # (docs/tracking.md, "Local mapping"), so it is an option, off by default.
        problem = BAProblem({k: m.keyframes[k].T_world_cam for k in allk}, set(fixed),
                            {p: points[p].xyz for p in pts.tolist()}, okf, opt,
                            ouv.reshape(-1, 2), our.astype(np.float64),
                            obs_sigma=self.backend.pixel_sigma * osg if self.cfg.level_sigma else None,
                            links=links or None)
        if self.lines is not None:
            problem.lines = self.lines.ba_problem(allk)
        return problem, okf, opt, fixed, chain

    def _apply_ba(self, problem: BAProblem, res, okf: np.ndarray, opt: np.ndarray, fixed: list[int]) -> None:
        if self.lines is not None:
            self.lines.apply_ba(problem.lines, getattr(res, "lines", {}), getattr(res, "line_inliers", None), res.poses)
        self.map.apply_adjustment(res.poses, res.points, res.inliers, okf, opt, set(fixed), getattr(res, "depth_only", None))
