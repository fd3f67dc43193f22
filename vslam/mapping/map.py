"""The map: keyframes, map points and the covisibility between keyframes.

One ``Map`` object, used single-threaded. Ids increase from 0 and dicts keep
insertion order, so every iteration (and therefore every run) is deterministic.
Covisibility is derived from point observations on demand rather than cached:
keyframes have a few hundred points, so counting is cheap and never stale.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from itertools import chain

import numpy as np

from vslam.features.base import Features
from vslam.features.matching import descriptor_rows


def _argmin_median(dist: np.ndarray) -> np.ndarray:
    """``np.argmin(np.median(dist, axis=2), axis=1)`` for integer (G,n,n) distances without float medians: the
    median of n integers is the middle one (n odd) or half the sum of the middle two (n even), both exact, so
    the middle value (or sum) orders the rows as the medians do, ties (first row wins) included."""
    h = dist.shape[2] // 2
    if dist.shape[2] % 2:
        mid = np.partition(dist, h, axis=2)[:, :, h]
    else:
        part = np.partition(dist, (h - 1, h), axis=2)
        mid = part[:, :, h - 1] + part[:, :, h]
    return np.argmin(mid, axis=1)


@dataclass
class KeyFrame:
    """A frame kept in the map.

    T_world_cam: (4,4) pose of cam0. features: its keypoints. depth: (N,) metres (NaN unknown);
    ur: (N,) virtual right x in pixels (NaN for monocular measurements);
    point_ids: (N,) int64 map-point id observed by each keypoint, -1 for none.
    velocity: (3,) world m/s of the body (IMU) and bias: (6,) accel m/s^2 then gyro rad/s -- the inertial
    state, set once visual-inertial mode is initialised (``vslam.tracking.vio``), None otherwise.
    """

    id: int
    frame_index: int
    timestamp: float
    T_world_cam: np.ndarray
    features: Features
    depth: np.ndarray
    ur: np.ndarray
    point_ids: np.ndarray
    velocity: np.ndarray | None = None
    bias: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(np.count_nonzero(self.point_ids >= 0))


@dataclass
class MapPoint:
    """A 3-D point: xyz (3,) world metres; descriptor (D,) representative of its observations;
    observations {kf_id: keypoint index}; n_visible / n_found: times it projected into a tracked
    frame / was matched there (their ratio drives culling); first_kf: keyframe that created it."""

    id: int
    xyz: np.ndarray
    descriptor: np.ndarray
    first_kf: int
    observations: dict[int, int] = field(default_factory=dict)
    n_visible: int = 1
    n_found: int = 1

    @property
    def found_ratio(self) -> float:
        return self.n_found / max(self.n_visible, 1)


@dataclass(frozen=True, eq=False)
class PoseLink:
    """A relative pose measured between keyframes ``a`` and ``b`` without map points (the dense depth step):
    T_a_b (4,4) and its covariance (6,6: rotation rad, translation m, right perturbation of T_a_b, as a GTSAM
    BetweenFactorPose3). Local and global BA hold the two keyframes to it beside whatever points they share."""

    a: int
    b: int
    T_a_b: np.ndarray
    cov: np.ndarray


class Map:
    """Keyframes and map points with consistent two-way bookkeeping of observations."""

    def __init__(self) -> None:
        self.keyframes: dict[int, KeyFrame] = {}
        self.points: dict[int, MapPoint] = {}
        self._next_kf = 0
        self._next_pt = 0
        # Bumped by every change of observations, point positions or descriptors (writers outside this class
        # call ``touch``): what tracking derived from the map stays valid while it is unchanged.
        self.revision = 0
        self._local_memo: tuple | None = None  # (revision, arguments, result) of the last ``local_map``
        self.links: list[PoseLink] = []  # keyframe-to-keyframe relative poses (``PoseLink``)

    def touch(self) -> None:
        """Mark the map changed (for code that moves points or keyframes directly)."""
        self.revision += 1

    def successor(self) -> Map:
        """An empty map whose keyframe and point ids continue this one's: the maps of one run (``Atlas``) never
        share an id, so frames, keyframes and points keep theirs when two maps are merged."""
        m = Map()
        m._next_kf, m._next_pt = self._next_kf, self._next_pt
        return m

    def continue_ids(self, other: Map) -> None:
        """New keyframe and point ids continue after ``other``'s as well as this map's own (a map taken up again
        after ``other`` was built)."""
        self._next_kf = max(self._next_kf, other._next_kf)
        self._next_pt = max(self._next_pt, other._next_pt)

    def absorb(self, other: Map, T_this_other: np.ndarray, scale: float = 1.0) -> None:
        """Move every keyframe and point of ``other`` into this map, expressed in this map's frame (x <- s R x + t:
        ``scale`` for a monocular map, whose unit is its own); ``other`` is left empty. The two maps share no
        observation yet: the caller fuses the seam."""
        R, t = T_this_other[:3, :3], T_this_other[:3, 3]
        for k, kf in other.keyframes.items():
            T = np.eye(4)
            T[:3, :3] = R @ kf.T_world_cam[:3, :3]
            T[:3, 3] = scale * (R @ kf.T_world_cam[:3, 3]) + t
            kf.T_world_cam = T
            if kf.velocity is not None:  # visual-inertial: a world-frame vector
                kf.velocity = scale * (R @ kf.velocity)
            if scale != 1.0:
                kf.depth = kf.depth * scale
            self.keyframes[k] = kf
        for p, mp in other.points.items():
            mp.xyz = scale * (R @ mp.xyz) + t
            self.points[p] = mp
        for ln in other.links:  # a rigid move keeps relative poses; a scale stretches their translation
            T = ln.T_a_b.copy()
            T[:3, 3] *= scale
            cov = ln.cov.copy()
            cov[3:, :] *= scale
            cov[:, 3:] *= scale
            self.links.append(PoseLink(ln.a, ln.b, T, cov))
        other.links = []
        self.continue_ids(other)
        other.keyframes, other.points = {}, {}
        self.revision += 1
        other.revision += 1

    # -- creation / removal ------------------------------------------------
    def add_keyframe(self, frame_index: int, timestamp: float, T_world_cam: np.ndarray, features: Features,
                     depth: np.ndarray, ur: np.ndarray) -> KeyFrame:
        kf = KeyFrame(self._next_kf, frame_index, timestamp, np.array(T_world_cam, dtype=np.float64), features,
                      depth, ur, np.full(len(features), -1, np.int64))
        self.keyframes[kf.id] = kf
        self._next_kf += 1
        self.revision += 1
        return kf

    def add_point(self, xyz: np.ndarray, kf_id: int, kp_idx: int) -> MapPoint:
        """A new point first seen by keyframe ``kf_id`` at keypoint ``kp_idx``."""
        kf = self.keyframes[kf_id]
        mp = MapPoint(self._next_pt, np.array(xyz, dtype=np.float64), kf.features.desc[kp_idx].copy(), kf_id)
        self.points[mp.id] = mp
        self._next_pt += 1
        self.add_observation(mp.id, kf_id, kp_idx)
        return mp

    def add_points(self, xyz: np.ndarray, kf_id: int, kp_idx: np.ndarray) -> list[int]:
        """``add_point`` for many keypoints of one keyframe, none of them a map point yet (same ids, same map;
        ~3x fewer Python steps: a keyframe creates up to ``max_new_points``). -> the new ids."""
        kf = self.keyframes[kf_id]
        kps = np.asarray(kp_idx, np.int64).reshape(-1)
        if np.any(kf.point_ids[kps] >= 0) or np.unique(kps).size != kps.size:
            raise ValueError(f"add_points: keyframe {kf_id}'s keypoints must be distinct and not yet map points")
        X = np.array(xyz, dtype=np.float64).reshape(-1, 3)
        D = kf.features.desc[kps]  # a copy: the points' descriptors must not follow the keyframe's array
        ids = list(range(self._next_pt, self._next_pt + kps.size))
        points = self.points
        for pid, x, d, kp in zip(ids, X, D, kps.tolist()):  # rows of X and D, as X[i] and D[i]
            points[pid] = MapPoint(pid, x, d, kf_id, {kf_id: kp})
        kf.point_ids[kps] = np.arange(self._next_pt, self._next_pt + kps.size)
        self._next_pt += kps.size
        self.revision += kps.size
        return ids

    def add_free_observations(self, pt_ids: list[int], kf_id: int, kp_idx: np.ndarray) -> None:
        """``add_observation`` for points not yet seen by ``kf_id`` at distinct keypoints of it that observe
        nothing (just-triangulated points in their second view): the same bookkeeping without the checks."""
        kf = self.keyframes[kf_id]
        kps = np.asarray(kp_idx, np.int64).reshape(-1)
        if len(pt_ids) != kps.size or np.any(kf.point_ids[kps] >= 0) or np.unique(kps).size != kps.size:
            raise ValueError(f"add_free_observations: keyframe {kf_id}'s keypoints must be distinct and free")
        points = self.points
        for pid, kp in zip(pt_ids, kps.tolist()):
            obs = points[pid].observations
            if kf_id in obs:
                raise ValueError(f"add_free_observations: point {pid} is already seen by keyframe {kf_id}")
            obs[kf_id] = kp
        kf.point_ids[kps] = pt_ids
        self.revision += kps.size

    def add_observation(self, pt_id: int, kf_id: int, kp_idx: int) -> None:
        kf, mp = self.keyframes[kf_id], self.points[pt_id]
        self.revision += 1
        old = int(kf.point_ids[kp_idx])
        if old >= 0 and old != pt_id:
            self.remove_observation(old, kf_id)
        if kf_id in mp.observations and mp.observations[kf_id] != kp_idx:  # one keypoint per point per keyframe
            kf.point_ids[mp.observations[kf_id]] = -1
        mp.observations[kf_id] = int(kp_idx)
        kf.point_ids[kp_idx] = pt_id

    def remove_observation(self, pt_id: int, kf_id: int) -> None:
        """Drop one observation; a point left with none is removed."""
        mp = self.points.get(pt_id)
        if mp is None or kf_id not in mp.observations:
            return
        kp = mp.observations.pop(kf_id)
        kf = self.keyframes[kf_id]
        self.revision += 1
        if kf.point_ids[kp] == pt_id:
            kf.point_ids[kp] = -1
        if not mp.observations:
            del self.points[pt_id]

    def remove_point(self, pt_id: int) -> None:
        mp = self.points.pop(pt_id, None)
        if mp is None:
            return
        self.revision += 1
        for kf_id, kp in mp.observations.items():
            kf = self.keyframes[kf_id]
            if kf.point_ids[kp] == pt_id:
                kf.point_ids[kp] = -1

    def merge_points(self, keep: int, drop: int) -> None:
        """Fuse duplicate ``drop`` into ``keep`` (observations move unless keep is already seen by that keyframe)."""
        if keep == drop or keep not in self.points or drop not in self.points:
            return
        mp_drop = self.points[drop]
        obs = list(mp_drop.observations.items())
        self.remove_point(drop)
        mk = self.points[keep]
        for kf_id, kp in obs:
            if kf_id not in mk.observations and self.keyframes[kf_id].point_ids[kp] < 0:
                self.add_observation(keep, kf_id, kp)
        mk.n_visible += mp_drop.n_visible
        mk.n_found += mp_drop.n_found

    def fuse_matches(self, kf_id: int, point_ids: np.ndarray) -> None:
        """Keyframe ``kf_id``'s keypoints matched to ``point_ids`` (-1: none) by a loop or a map merge: each
        becomes an observation of its matched point, and a point the keypoint already had is merged into the
        matched one (the matched, older side is kept)."""
        kf = self.keyframes[kf_id]
        for kp in np.flatnonzero(point_ids >= 0).tolist():
            pid, mine = int(point_ids[kp]), int(kf.point_ids[kp])
            if pid not in self.points:
                continue
            if mine < 0:
                self.add_observation(pid, kf_id, kp)
            elif mine != pid and mine in self.points:
                self.merge_points(pid, mine)

    # -- queries -------------------------------------------------------------
    def covisibility(self, kf_id: int) -> dict[int, int]:
        """{other keyframe id: number of map points it shares with ``kf_id``}, ordered by id."""
        kf = self.keyframes[kf_id]
        counts = self.observers(kf.point_ids[kf.point_ids >= 0])
        counts.pop(kf_id, None)
        return dict(sorted(counts.items()))

    def observers(self, pt_ids: np.ndarray) -> Counter:
        """{keyframe id: how many of the points ``pt_ids`` it observes} (Counter counts in C, not per Python step)."""
        points = self.points
        return Counter(chain.from_iterable(points[p].observations for p in np.asarray(pt_ids).tolist()))

    def covisible_keyframes(self, kf_id: int, min_shared: int = 15, limit: int | None = None) -> list[int]:
        """Keyframes sharing >= min_shared points with ``kf_id``, most shared first (ties: newest first)."""
        cov = [(n, k) for k, n in self.covisibility(kf_id).items() if n >= min_shared]
        cov.sort(key=lambda nk: (-nk[0], -nk[1]))
        ids = [k for _, k in cov]
        return ids if limit is None else ids[:limit]

    def local_map(self, kf_id: int, max_keyframes: int = 20, min_shared: int = 15) -> tuple[list[int], np.ndarray]:
        """(keyframe ids: ``kf_id`` + its most covisible, point ids they observe (sorted, unique, read-only)).

        Remembered while the map is unchanged (``revision``): point and line tracking ask for the same local
        map on every frame between keyframes (covisibility counting each time)."""
        key = (self.revision, kf_id, max_keyframes, min_shared)
        if self._local_memo is not None and self._local_memo[0] == key:
            return list(self._local_memo[1]), self._local_memo[2]
        kfs = [kf_id] + self.covisible_keyframes(kf_id, min_shared, max_keyframes - 1)
        pids = [self.keyframes[k].point_ids for k in kfs]
        allp = np.unique(np.concatenate(pids)) if pids else np.zeros(0, np.int64)
        allp = allp[allp >= 0]
        allp.flags.writeable = False
        self._local_memo = (key, kfs, allp)
        return list(kfs), allp

    def existing(self, ids: np.ndarray) -> np.ndarray:
        """The ids of ``ids`` still in the map, in order (a merge or a cull may have removed some since)."""
        ids = np.asarray(ids, np.int64)
        return ids[np.fromiter(map(self.points.__contains__, ids.tolist()), bool, len(ids))]

    def points_xyz(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids),3) world positions."""
        if len(ids) == 0:
            return np.zeros((0, 3))
        points = self.points
        # one concatenation of the (3,) rows: faster than np.array of the list or np.stack (docs/speed.md)
        return np.concatenate([points[i].xyz for i in np.asarray(ids).tolist()], dtype=np.float64).reshape(-1, 3)

    def descriptors(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids),D) descriptors of points ``ids``."""
        if len(ids) == 0:
            return np.array([])
        points = self.points
        rows = [points[i].descriptor for i in np.asarray(ids).tolist()]
        return np.concatenate(rows).reshape(len(rows), -1)  # as np.array(rows), faster (docs/speed.md)

    def update_descriptor(self, pt_id: int) -> None:
        """Representative descriptor: the observation with the smallest median distance to the others (ORB-SLAM)."""
        mp = self.points[pt_id]
        if len(mp.observations) < 3:
            return
        self.revision += 1
        D = np.stack([self.keyframes[k].features.desc[i] for k, i in mp.observations.items()])
        n = len(D)
        a, b = np.repeat(np.arange(n), n), np.tile(np.arange(n), n)
        dist = descriptor_rows(D[a], D[b]).reshape(n, n)
        mp.descriptor = D[int(np.argmin(np.median(dist, axis=1)))].copy()

    def update_descriptors(self, pt_ids) -> None:
        """``update_descriptor`` for many points at once (same result): binary descriptors of the points with
        the same number of observations are compared in one popcount over the group (~10x fewer Python steps)."""
        groups: dict[int, list[int]] = {}
        self.revision += 1
        points = self.points
        for pid in np.asarray(pt_ids).tolist():
            n = len(points[pid].observations)
            if n >= 3:
                groups.setdefault(n, []).append(pid)
        kfs = self.keyframes
        for n, ids in groups.items():
            rows = [kfs[k].features.desc[i] for p in ids for k, i in points[p].observations.items()]
            # (G, n, D); one concatenation of the flat list of rows: faster than np.array of it or nested stacks
            D = np.concatenate(rows).reshape(len(ids), n, -1)
            if D.dtype != np.uint8 or D.shape[2] % 8:
                for p in ids:
                    self.update_descriptor(p)
                continue
            w = np.ascontiguousarray(D).view(np.uint64)  # (G, n, D/8)
            dist = np.bitwise_count(w[:, :, None, :] ^ w[:, None, :, :]).sum(axis=3, dtype=np.int32)
            best = _argmin_median(dist)
            for p, row, b in zip(ids, D, best.tolist()):
                self.points[p].descriptor = row[b].copy()

    def apply_adjustment(self, poses: dict, points: dict, inliers: np.ndarray, obs_kf, obs_pt, fixed=(),
                         depth_only: np.ndarray | None = None) -> None:
        """Write a bundle adjustment back: keyframe poses (not those in ``fixed``), the points still in the map,
        and drop the observations (obs_kf[i], obs_pt[i]) the BA classified as outliers (``inliers[i]`` False)."""
        self.revision += 1
        for k, T in poses.items():
            if k not in fixed:
                self.keyframes[k].T_world_cam = np.asarray(T, dtype=np.float64)
        mine, asarray, f64 = self.points, np.asarray, np.float64  # a local BA writes back ~1000 points
        for p, X in points.items():
            mp = mine.get(p)
            if mp is not None:
                mp.xyz = asarray(X, dtype=f64)
        for i in np.flatnonzero(~np.asarray(inliers, bool)):
            if depth_only is not None and depth_only[i]:  # keep the match as a mono observation
                mp = self.points.get(int(obs_pt[i]))
                kp = None if mp is None else mp.observations.get(int(obs_kf[i]))
                if kp is not None:
                    self.keyframes[int(obs_kf[i])].ur[kp] = np.nan
                    continue
            self.remove_observation(int(obs_pt[i]), int(obs_kf[i]))

    def stats(self) -> dict[str, int]:
        n_obs = sum(len(p.observations) for p in self.points.values())
        return {"keyframes": len(self.keyframes), "points": len(self.points), "observations": n_obs,
                "pose_links": len(self.links)}
