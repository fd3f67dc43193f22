"""Several maps in one run (ORB-SLAM3's Atlas): a new map when tracking is lost, maps merged when they meet.

Whatever stops tracking -- a gap in the recording, a fast turn, a white wall, a person filling the view --
the tracker does not extrapolate for ever: once every recovery step has failed for ``new_map_after_s``, the
current map is archived here and a new one starts (RGB-D / stereo: from the frame's own depth, at once;
monocular: at the next successful two-view initialisation). Every new keyframe of the current map is then
looked for in the archived maps by its place descriptor (bag of words over its ORB descriptors, or the loop
closer's database when that is on); candidates confirmed by descriptor matching + PnP + the local-map round
against that map's points (``Atlas.locate``, also the relocalisation step) give the rigid transform between the
two maps, and the current map is moved into the old one (``Map.absorb``): the seam's duplicate points are fused
and a global BA re-fits the merged map, as after a loop (``MapRecovery._merge``). Monocular maps have a unit of
their own each: the transform is a similarity, its scale the median depth ratio of the keypoints' points in the
two maps (``Atlas.scale``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from vslam.backend.ba import BackendConfig, StereoCamera
from vslam.data.types import PinholeCamera
from vslam.features.base import Features
from vslam.features.matching import match_mutual
from vslam.geometry.se3 import so3_angle_deg
from vslam.loop.database import KeyframeDatabase
from vslam.loop.node_match import CoarseNodes, match_in_nodes
from vslam.loop.vocabulary import Vocabulary, default_vocabulary_path
from vslam.mapping.map import Map
from vslam.tracking.tracker import TrackingConfig, Tracker, TrackResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AtlasConfig:
    """``slam.atlas``: what happens when tracking is lost.

    new_map_after_s: every recovery step (motion model, reference keyframe, newest keyframes, place
        relocalisation) has failed this long since the last tracked frame: archive the map, start a new one
        from the first frame that can make one (RGB-D / stereo: ``min_points`` keypoints with depth; monocular:
        re-initialise). A gap in the images longer than this starts one at the first frame after it. Short
        enough that a lost camera is never extrapolated for long (30 Hz: 3 frames), long enough that one
        blurred frame does not split the map.
    bridge_s: the longest a frame is "predicted" (motion model) while no new map can start; later frames
        have no pose ("lost": in stats.csv, not in the trajectory).
    min_points: keypoints with depth a frame needs to start a new map (ORB-SLAM3 asks 500 keypoints): a
        blurred or dark frame's few corners would make a map nothing can track against.
    merge: look for each new keyframe in the archived maps and merge on a confirmed match (RGB-D, stereo).
    merge_top_k: archived keyframes tried per new keyframe, best place-descriptor score first.
    merge_min_inliers: points the PnP + local-map round must keep for a merge: more than tracking's 20, since
        a wrong merge bends two maps together.
    merge_min_score: place-descriptor similarity floor of a candidate.
    merge_consistency: new keyframes in a row that must each find the same archived map, with transforms
        between the maps that agree (``merge_agree_deg`` / ``merge_agree_m``), before the maps merge: one
        verified match can be a look-alike place (ORB-SLAM asks the same of loop candidates).
    merge_agree_deg, merge_agree_m: how far two keyframes' map-to-map transforms may differ and still agree
        (rotation; translation, not compared for monocular maps, whose unit is their own).
    min_lost_frames: frames not tracked in a row before a new map starts, besides ``new_map_after_s``: at a
        low frame rate (0.5-1 s between frames) one frame the tracker cannot measure is otherwise a new map,
        where the next frame would have been tracked in the old one again.
    relocalise: a frame the current map cannot measure is looked for in the archived maps (place retrieval,
        then descriptor matching + PnP + the local-map round of ``Tracker.track_keyframe``); found, that map
        becomes the current one again and the frame continues it (the map it leaves is archived).
    relocalise_min_inliers: points the local-map round must keep to switch maps: more than tracking's 20, as
        a wrong switch puts the camera in another place.
    match_nodes, match_probes: binary descriptors are matched to an archived map only within the same coarse
        vocabulary node (``vslam.loop.node_match``; ORB-SLAM's SearchByBoW), each query keypoint looked for in its
        ``match_probes`` nearest of ``match_nodes`` nodes; 0 nodes: every pair compared (about 4x the time).
    """

    enabled: bool = True
    new_map_after_s: float = 0.1
    bridge_s: float = 1.0
    min_points: int = 300
    merge: bool = True
    merge_top_k: int = 5
    merge_min_inliers: int = 60
    merge_min_score: float = 0.05
    merge_consistency: int = 2
    merge_agree_deg: float = 5.0
    merge_agree_m: float = 0.2
    min_lost_frames: int = 2
    relocalise: bool = True
    relocalise_min_inliers: int = 40
    match_nodes: int = 16
    match_probes: int = 3


class Atlas:
    """The archived maps of a run and their keyframe databases."""

    def __init__(self, cfg: AtlasConfig, cam: PinholeCamera, stereo_cam: StereoCamera, tracking: TrackingConfig,
                 backend: BackendConfig, descriptor=None):
        self.cfg, self.cam, self.stereo_cam, self.tracking, self.backend = cfg, cam, stereo_cam, tracking, backend
        self.descriptor = descriptor  # PlaceDescriptor of the keyframes (None: maps are kept, never merged)
        self.maps: dict[int, Map] = {}
        self.dbs: dict[int, KeyframeDatabase] = {}
        self.parent: dict[int, int] = {}  # map id -> the map it was merged into
        self.n_maps = 1  # ids handed out so far (map 0 is the first)
        self.merges: list[tuple[int, int, int, int]] = []  # (merged map, into map, query kf, candidate kf)
        self.switches = 0  # frames relocalised into an archived map, which then continued
        # (archived map id, T_old_new) of the last keyframes that found it in a row (``merge_consistency``)
        self.votes: list[tuple[int, np.ndarray]] = []
        self._indexes: dict[int, _MapIndex] = {}  # archived map id -> its points for ``locate``
        self._nodes: CoarseNodes | None = None  # built on the first query with binary descriptors

    def new_id(self) -> int:
        self.n_maps += 1
        return self.n_maps - 1

    def final_id(self, map_id: int) -> int:
        """The map that ``map_id`` ended in after the merges."""
        while map_id in self.parent:
            map_id = self.parent[map_id]
        return map_id

    def archive(self, map_id: int, m: Map, db: KeyframeDatabase | None = None) -> None:
        """Keep ``m`` (and its place database; built from its keyframes when not given)."""
        if not m.keyframes:
            return
        self.maps[map_id] = m
        if self.descriptor is None:
            return
        if db is None:
            db = KeyframeDatabase(self.descriptor.dim)
            for k, kf in m.keyframes.items():
                db.add(k, self.descriptor.describe(None, kf.features))
        self.dbs[map_id] = db
        log.info("map %d archived: %d keyframes, %d points", map_id, len(m.keyframes), len(m.points))

    def describe(self, features: Features, image: np.ndarray | None = None) -> np.ndarray | None:
        return None if self.descriptor is None else self.descriptor.describe(image, features)

    def locate(self, feats: Features, ur: np.ndarray, vec: np.ndarray, min_inliers: int | None = None,
               method: str = "merge", ratio: float = 0.8) -> tuple[int, int, TrackResult] | None:
        """The archived map a keyframe or frame (keypoints ``feats``, virtual right ``ur``, descriptor ``vec``) is
        seen in: (map id, candidate keyframe, its pose there), or None. ``min_inliers``: default
        ``merge_min_inliers``; ``ratio``: of the descriptor matching.

        Per map, the ``merge_top_k`` best place candidates are verified together: the keypoints are matched once
        against the map points the candidates see (each point once; binary descriptors within coarse vocabulary
        nodes, ``match_nodes``), then PnP and the local-map round of the candidate that sees most of the PnP
        inliers. Matching is most of the cost, and the candidates of one place share most of their points, so
        one matching over their union costs what two or three keyframes' cost apart (docs/tracking.md, "The
        archived-map query")."""
        if vec is None or len(feats) < self.tracking.min_inliers:
            return None
        need = self.cfg.merge_min_inliers if min_inliers is None else min_inliers
        probes = self._probes(feats)
        tree = None
        for map_id in sorted(self.maps, reverse=True):  # the most recent map first
            db = self.dbs.get(map_id)
            if db is None or not len(db):
                continue
            cands = [k for k, _ in db.query(vec, self.cfg.merge_top_k, min_score=self.cfg.merge_min_score)]
            if not cands:
                continue
            index = self._index(map_id)
            rows = index.rows(cands)
            if probes is None:
                pair = match_mutual(index.desc[rows], feats.desc, ratio=ratio, max_dist=self.tracking.max_hamming)
            else:
                pair = match_in_nodes(index.desc[rows], index.nodes(self._nodes)[rows], feats.desc, probes, ratio,
                                      self.tracking.max_hamming)
            if len(pair) < self.tracking.min_inliers:
                continue
            tracker = index.tracker
            rows, kps = rows[pair[:, 0]], pair[:, 1]
            T, inl = tracker.pnp(feats.uv[kps], index.xyz[rows])
            if T is None:
                continue
            pids = index.ids[rows[inl]]
            T_ref, inl2 = tracker.refine(T, pids, kps[inl], ur, feats, index.xyz[rows[inl]])
            cand = index.best_candidate(cands, pids)
            tree = cKDTree(feats.uv) if tree is None else tree
            # as ``Tracker.track_keyframe``: the local-map round from the refined pose unless the refinement's
            # depth residuals dropped too many matches, then from the RANSAC pose
            T0 = T_ref if inl2.sum() >= self.tracking.min_inliers else T
            res = tracker.finish_local(T0, feats, ur, cand, tree, method)
            if res.ok and res.n_inliers >= need:
                return map_id, cand, res
        return None

    def _probes(self, feats: Features) -> np.ndarray | None:
        """(N,t) coarse nodes each keypoint is looked for in (``match_nodes``), or None: every pair is compared
        (learned float descriptors, or ``match_nodes`` 0). The nodes come from the BoW descriptor's vocabulary,
        else the shipped one."""
        if self.cfg.match_nodes <= 0 or feats.desc.dtype != np.uint8:
            return None
        if self._nodes is None:
            vocab = getattr(self.descriptor, "vocab", None)
            self._nodes = CoarseNodes(vocab if vocab is not None else Vocabulary.load(default_vocabulary_path()),
                                      self.cfg.match_nodes)
        return self._nodes.nodes(feats.desc, self.cfg.match_probes)

    def _index(self, map_id: int) -> _MapIndex:
        """The matching data of archived map ``map_id``, built on its first query (an archived map does not
        change until it is taken up again)."""
        m = self.maps[map_id]
        index = self._indexes.get(map_id)
        if index is None or index.map is not m or index.revision != m.revision:
            index = _MapIndex(m, Tracker(m, self.cam, self.stereo_cam, self.tracking, self.backend))
            self._indexes[map_id] = index
        return index

    @staticmethod
    def old_from_new(T_new: np.ndarray, T_old: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """(R, t) of the similarity x_old = scale R x_new + t that takes a camera at ``T_new`` in the new map to
        ``T_old`` in the old one, as a 4x4 (its rotation and translation; the scale apart)."""
        T = np.eye(4)
        T[:3, :3] = T_old[:3, :3] @ T_new[:3, :3].T
        T[:3, 3] = T_old[:3, 3] - scale * (T[:3, :3] @ T_new[:3, 3])
        return T

    @staticmethod
    def yaw_only(T_old_new: np.ndarray, T_new: np.ndarray) -> np.ndarray:
        """``T_old_new`` with its rotation reduced to the turn about the world's z (gravity) axis, its translation
        refitted so the keyframe's centre (``T_new``'s) still lands where it did: two maps that both hang from an
        IMU's gravity differ by yaw and translation only (ORB-SLAM3's inertial merge), and a roll or pitch
        taken from one keyframe's visual pose would tilt the merged map against the gravity its IMU factors
        assume."""
        R = T_old_new[:3, :3]
        yaw = np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])  # the z rotation nearest R (least squares)
        c, s = np.cos(yaw), np.sin(yaw)
        T = np.eye(4)
        T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        centre_old = T_old_new[:3, :3] @ T_new[:3, 3] + T_old_new[:3, 3]
        T[:3, 3] = centre_old - T[:3, :3] @ T_new[:3, 3]
        return T

    @staticmethod
    def scale(old: Map, new: Map, kf, res: TrackResult, min_points: int = 20) -> float | None:
        """Monocular: length in the old map per length in the new one -- the median ratio of the depths, in the
        keyframe's camera, of the same keypoints' two points (the old map's at the located pose, the new map's
        at the keyframe's own pose; as ``LoopCloser.loop_scale``). None when fewer than ``min_points``."""
        kp = np.flatnonzero((res.point_ids >= 0) & (kf.point_ids >= 0))
        kp = np.array([k for k in kp.tolist() if int(res.point_ids[k]) in old.points and int(kf.point_ids[k]) in new.points],
                      np.int64)
        if len(kp) < min_points:
            return None
        Tn, To = np.linalg.inv(kf.T_world_cam), np.linalg.inv(res.T_world_cam)
        zn = (new.points_xyz(kf.point_ids[kp]) @ Tn[:3, :3].T + Tn[:3, 3])[:, 2]
        zo = (old.points_xyz(res.point_ids[kp]) @ To[:3, :3].T + To[:3, 3])[:, 2]
        good = (zn > 0) & (zo > 0)
        if int(good.sum()) < min_points:
            return None
        return float(np.median(zo[good] / zn[good]))

    def vote(self, map_id: int, T_old_new: np.ndarray, metric: bool) -> bool:
        """A new keyframe found archived map ``map_id`` with map-to-map transform ``T_old_new`` -> whether the
        last ``merge_consistency`` keyframes (this one included) all found it, with agreeing transforms."""
        if self.votes:
            last_id, T_last = self.votes[-1]
            angle = so3_angle_deg(T_last[:3, :3].T @ T_old_new[:3, :3])
            far = metric and float(np.linalg.norm(T_last[:3, 3] - T_old_new[:3, 3])) > self.cfg.merge_agree_m
            if last_id != map_id or angle > self.cfg.merge_agree_deg or far:
                self.votes = []
        self.votes.append((map_id, T_old_new))
        return len(self.votes) >= self.cfg.merge_consistency

    def take(self, map_id: int) -> tuple[Map, KeyframeDatabase | None]:
        """Remove an archived map (it becomes the current one again, with the current map merged into it)."""
        self._indexes.pop(map_id, None)
        return self.maps.pop(map_id), self.dbs.pop(map_id, None)


class _MapIndex:
    """An archived map's points as arrays for ``Atlas.locate``: ids (P,) sorted, desc (P,D) representative
    descriptors, xyz (P,3) world positions; per keyframe the rows of the points it sees (built on first use);
    the map's ``Tracker`` (its local-map cache stays valid while the map is unchanged)."""

    def __init__(self, m: Map, tracker: Tracker):
        self.map, self.revision, self.tracker = m, m.revision, tracker
        self.ids = np.array(sorted(m.points), np.int64)
        self.desc = m.descriptors(self.ids)
        self.xyz = m.points_xyz(self.ids)
        self._kf_rows: dict[int, np.ndarray] = {}
        self._nodes: np.ndarray | None = None

    def nodes(self, coarse: CoarseNodes) -> np.ndarray:
        """(P,) the nearest coarse node of each point's descriptor."""
        if self._nodes is None:
            self._nodes = coarse.nodes(self.desc)[:, 0]
        return self._nodes

    def kf_rows(self, kf_id: int) -> np.ndarray:
        """Rows of the points keyframe ``kf_id`` sees (ascending)."""
        rows = self._kf_rows.get(kf_id)
        if rows is None:
            pids = self.map.keyframes[kf_id].point_ids
            pids = np.unique(pids[pids >= 0])
            rows = np.searchsorted(self.ids, pids)
            rows = rows[(rows < len(self.ids)) & (self.ids[np.minimum(rows, len(self.ids) - 1)] == pids)]
            self._kf_rows[kf_id] = rows
        return rows

    def rows(self, kf_ids: list[int]) -> np.ndarray:
        """Rows of the points any of ``kf_ids`` sees, each once, ascending."""
        return np.unique(np.concatenate([self.kf_rows(k) for k in kf_ids]))

    def best_candidate(self, kf_ids: list[int], pids: np.ndarray) -> int:
        """The keyframe of ``kf_ids`` (best place score first) that sees most of the points ``pids``; ties: the
        better score."""
        hits = [int(np.isin(self.ids[self.kf_rows(k)], pids, assume_unique=True).sum()) for k in kf_ids]
        return kf_ids[int(np.argmax(hits))]
