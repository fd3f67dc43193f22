"""Loop closing and place-recognition relocalisation over one map (ORB-SLAM's LoopClosing, synchronous).

Per new keyframe (``LoopCloser.add_keyframe``):

1. *Describe* it with the ``PlaceDescriptor`` and query the keyframe database
   before adding it (so it never finds itself).
2. *Detect*: candidates scoring above both ``min_score`` and the lowest score
   of the keyframe's own covisible neighbours (ORB-SLAM's relative floor: a
   loop must look at least as similar as the keyframes it already shares points
   with), older by ``min_kf_gap`` keyframes and not covisible; then temporal
   consistency -- the candidate's covisibility group must overlap a group
   accepted for the previous ``consistency - 1`` keyframes.
3. *Verify* geometrically (``vslam.loop.verify``).
4. *Correct* (RGB-D / stereo): pose graph over all keyframes (consecutive +
   strong covisibility edges measured from the poses before the correction,
   every accepted loop edge so far), first keyframe fixed; every map point
   moves with its reference keyframe; the loop side's points are fused into
   the query keyframe and its neighbours (duplicates merged), then a local BA.
   Monocular (``mono_sim3``): the drift includes scale, so the loop is a
   similarity -- the verified pose (PnP on the old side's points) plus the
   scale from the median depth ratio of the same keypoints' points on the two
   sides -- and the graph is ORB-SLAM's Sim3 essential graph
   (``optimize_sim3_graph``); points follow their keyframe's similarity, the
   frames' relative poses their keyframe's scale (``FrameLog.scale_refs``).

Relocalisation (``relocalise``) ranks keyframes by the same descriptor and
tries the tracker's keyframe matching on the best few.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera, local_bundle_adjustment
from vslam.backend.pose_graph import PoseEdge, SimEdge, optimize_pose_graph, optimize_sim3_graph, sim_matrix, sim_parts
from vslam.data.types import PinholeCamera, SensorKind
from vslam.features.base import Features
from vslam.geometry.se3 import inv_T, make_T
from vslam.loop.config import LoopConfig
from vslam.loop.database import KeyframeDatabase
from vslam.loop.descriptor import PlaceDescriptor, make_place_descriptor
from vslam.loop.verify import LoopMatch, LoopVerifier
from vslam.mapping.map import KeyFrame, Map

log = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """Counters for reports: candidates that passed detection, loops verified, loops corrected, relocalisations."""

    candidates: int = 0
    verified: int = 0
    corrected: int = 0
    relocalised: int = 0
    loops: list[tuple[int, int]] = field(default_factory=list)  # (query kf, candidate kf)


class LoopCloser:
    """Owns the keyframe database and the accepted loop edges; mutates the map when a loop is closed."""

    def __init__(self, slam_map: Map, cam: PinholeCamera, stereo_cam: StereoCamera, sensor: SensorKind,
                 cfg: LoopConfig, backend: BackendConfig, mapper=None, descriptor: PlaceDescriptor | None = None):
        self.map, self.sensor, self.cfg, self.mapper, self.backend = slam_map, sensor, cfg, mapper, backend
        self.descriptor = descriptor if descriptor is not None else make_place_descriptor(cfg.descriptor, cfg.vocabulary, cfg.weights)
        self.db = KeyframeDatabase(self.descriptor.dim)
        self.verifier = LoopVerifier(cam, stereo_cam, cfg, backend)
        self.loop_edges: list[PoseEdge] = []
        self.sim_loop_edges: list[SimEdge] = []  # monocular loops (Sim3)
        self.frames = None  # the tracker's FrameLog: frames take their keyframe's scale after a Sim3 loop
        self.last_scale = 1.0  # scale the query keyframe took in the last correction (the tracker's velocity follows)
        self.stats = LoopStats()
        self._groups: list[tuple[set[int], int]] = []  # consistent candidate groups of the previous keyframe

    # -- detection --------------------------------------------------------------
    def detect(self, kf: KeyFrame, vec: np.ndarray) -> list[int]:
        """Candidate keyframe ids for ``kf`` (descriptor ``vec``) that are temporally consistent."""
        cfg = self.cfg
        neighbors = self.map.covisible_keyframes(kf.id, 1)
        scores = [float(self.db.vector(n) @ vec) for n in neighbors if n in self.db]
        floor = max(cfg.min_score, min(scores) if scores else cfg.min_score)
        exclude = set(neighbors) | {k for k in self.db.ids().tolist() if k > kf.id - cfg.min_kf_gap}
        cands = self.db.query(vec, cfg.top_k, exclude, floor)
        new_groups: list[tuple[set[int], int]] = []
        accepted: list[int] = []
        for c, _ in cands:
            group = {c, *self.map.covisible_keyframes(c, cfg.group_min_shared)}
            count = 1 + max((n for g, n in self._groups if g & group), default=0)
            new_groups.append((group, count))
            if count >= cfg.consistency:
                accepted.append(c)
        self._groups = new_groups
        return accepted

    def add_keyframe(self, kf: KeyFrame, image: np.ndarray | None = None) -> LoopMatch | None:
        """Describe, detect, verify and (RGB-D/stereo) correct. -> the accepted loop, or None."""
        vec = self.descriptor.describe(image, kf.features)
        cands = self.detect(kf, vec) if len(self.db) else []
        self.db.add(kf.id, vec)
        own = kf.point_ids[kf.point_ids >= 0]
        for c in cands:
            self.stats.candidates += 1
            match = self.verifier.verify(self.map, kf.features, kf.ur, c, exclude_points=own, max_kf=kf.id - self.cfg.min_kf_gap)
            if match is None:
                continue
            corr = float(np.linalg.norm(match.T_world_cam[:3, 3] - kf.T_world_cam[:3, 3]))
            if corr > self.cfg.max_correction_m:
                log.info("loop kf %d -> %d refused: correction %.2f m", kf.id, c, corr)
                continue
            self.stats.verified += 1
            self.stats.loops.append((kf.id, c))
            log.info("loop kf %d -> kf %d: %d inliers, correction %.3f m", kf.id, c, match.n_inliers, corr)
            if self.sensor != "mono":
                self.correct(kf, match)
                self.stats.corrected += 1
            elif self.cfg.mono_sim3:
                scale = self.loop_scale(kf, match)
                if scale is None:
                    log.info("loop kf %d -> %d: too few points on both sides for its scale; not corrected", kf.id, c)
                else:
                    self.correct_sim3(kf, match, scale)
                    self.stats.corrected += 1
            self._groups = []  # the next keyframes see the same place: no second loop on the same evidence
            return match
        return None

    # -- correction ---------------------------------------------------------------
    def pose_graph_edges(self, before: dict[int, np.ndarray]) -> list[PoseEdge]:
        """Consecutive-keyframe and strong-covisibility edges measured from ``before`` + accepted loop edges."""
        ids = sorted(before)
        edges = [PoseEdge(a, b, inv_T(before[a]) @ before[b]) for a, b in zip(ids[:-1], ids[1:])]
        for k in ids:
            for n, shared in self.map.covisibility(k).items():
                if n > k + 1 and shared >= self.cfg.covis_edge_min:
                    edges.append(PoseEdge(k, n, inv_T(before[k]) @ before[n]))
        return edges + self.loop_edges

    def correct(self, kf: KeyFrame, match: LoopMatch) -> None:
        m = self.map
        before = {k: f.T_world_cam.copy() for k, f in m.keyframes.items()}
        edges = self.pose_graph_edges(before)
        # initial guess: the query and its neighbours take the verified correction rigidly (ORB-SLAM)
        T_corr = match.T_world_cam @ inv_T(before[kf.id])
        guess = dict(before)
        group = self._loop_group(kf)
        for k in group:
            guess[k] = T_corr @ before[k]
        # One loop edge per keyframe of the corrected group (ORB-SLAM's loop connections). A single edge loses
        # against the chain: consecutive + covisibility edges make it several times stiffer than one edge, and
        # the pose graph then met only a small part of even the true loop pose (docs/loop.md, "Loop edges").
        c = match.candidate
        new = [PoseEdge(c, k, inv_T(before[c]) @ guess[k], loop=True) for k in group]
        after, e0, e1 = optimize_pose_graph(guess, edges + new, {min(m.keyframes)}, self.cfg.pose_graph)
        self.loop_edges.extend(new)
        log.debug("pose graph: %d keyframes, %d edges, error %.3g -> %.3g", len(after), len(edges) + len(new), e0, e1)
        for k, T in after.items():
            m.keyframes[k].T_world_cam = T
        self._points_follow({k: after[k] @ inv_T(before[k]) for k in after})
        self.fuse(kf, match)

    def _loop_group(self, kf: KeyFrame) -> list[int]:
        """The query keyframe and its neighbours: they take the verified correction as the initial guess and each
        gets a loop edge (ORB-SLAM's loop connections)."""
        return [kf.id, *self.map.covisible_keyframes(kf.id, self.cfg.group_min_shared, self.cfg.fuse_neighbors)]

    def _points_follow(self, delta: dict[int, np.ndarray]) -> None:
        """Every map point (and line) moves with its reference keyframe: x <- D x, D (4,4) rigid or similarity
        per keyframe."""
        m = self.map
        for mp in m.points.values():
            ref = mp.first_kf if mp.first_kf in m.keyframes else min(mp.observations)
            D = delta[ref]
            mp.xyz = D[:3, :3] @ mp.xyz + D[:3, 3]
        m.touch()
        if self.mapper is not None and self.mapper.lines is not None:
            self.mapper.lines.follow(delta)

    def loop_scale(self, kf: KeyFrame, match: LoopMatch) -> float | None:
        """Monocular: length in the old (candidate-side) map per length in the query's drifted map -- the median
        ratio of the depths, in the query camera, of the same keypoints' two points: the old-side point in the
        verified pose, the query's own point in its tracked pose. None when fewer than ``sim3_min_points``."""
        m = self.map
        kp = np.flatnonzero((match.point_ids >= 0) & (kf.point_ids >= 0) & (match.point_ids != kf.point_ids))
        kp = np.array([k for k in kp if int(kf.point_ids[k]) in m.points and int(match.point_ids[k]) in m.points], np.int64)
        if len(kp) < self.cfg.sim3_min_points:
            return None
        Tq, Tc = inv_T(kf.T_world_cam), inv_T(match.T_world_cam)
        zq = (m.points_xyz(kf.point_ids[kp]) @ Tq[:3, :3].T + Tq[:3, 3])[:, 2]
        zc = (m.points_xyz(match.point_ids[kp]) @ Tc[:3, :3].T + Tc[:3, 3])[:, 2]
        good = (zq > 0) & (zc > 0)
        if int(good.sum()) < self.cfg.sim3_min_points:
            return None
        return float(np.median(zc[good] / zq[good]))

    def correct_sim3(self, kf: KeyFrame, match: LoopMatch, scale: float) -> None:
        """Monocular loop: Sim3 essential graph, points and frames follow their keyframes (module doc)."""
        m = self.map
        before = {k: f.T_world_cam.copy() for k, f in m.keyframes.items()}
        S0 = {k: sim_matrix(T) for k, T in before.items()}
        # the query side's world -> the old side's: X_old = S_corr X_query
        S_corr = sim_matrix(match.T_world_cam, scale) @ np.linalg.inv(S0[kf.id])
        guess = dict(S0)
        group = self._loop_group(kf)
        for k in group:
            guess[k] = S_corr @ S0[k]
        edges = [SimEdge(e.i, e.j, sim_matrix(e.T_i_j)) for e in self.pose_graph_edges(before)]
        c = match.candidate
        new = [SimEdge(c, k, np.linalg.inv(S0[c]) @ guess[k], loop=True) for k in group]
        after, e0, e1 = optimize_sim3_graph(guess, edges + self.sim_loop_edges + new, {min(m.keyframes)},
                                            self.cfg.pose_graph, self.cfg.sim3_sigma_scale)
        self.sim_loop_edges.extend(new)
        log.info("Sim3 loop kf %d -> %d: scale %.3f, graph error %.3g -> %.3g", kf.id, c, scale, e0, e1)
        scales = {}
        for k, S in after.items():
            R, t, sk = sim_parts(S)
            m.keyframes[k].T_world_cam = make_T(R, t)
            scales[k] = sk
        self._points_follow({k: after[k] @ np.linalg.inv(S0[k]) for k in after})
        if self.frames is not None:
            self.frames.scale_refs(scales)
        self.last_scale = scales[kf.id]
        self.fuse(kf, match)

    def fuse(self, kf: KeyFrame, match: LoopMatch) -> None:
        """Merge the loop side's points with their duplicates on the query side (the older point is kept)."""
        m = self.map
        m.fuse_matches(kf.id, match.point_ids)  # the verified matches first
        if self.mapper is None:
            return
        loop_pids = self.verifier.candidate_points(m, match.candidate, kf.id - self.cfg.min_kf_gap)
        for t in [kf.id, *m.covisible_keyframes(kf.id, 1, self.cfg.fuse_neighbors)]:
            self.mapper._fuse_into(m.keyframes[t], loop_pids)
        for pid in np.unique(kf.point_ids[kf.point_ids >= 0]):
            m.update_descriptor(int(pid))
        if self.cfg.global_ba:
            self.global_bundle_adjust()
        elif self.cfg.local_ba and len(m.keyframes) >= 2:
            self.mapper.bundle_adjust(kf.id)

    def global_bundle_adjust(self) -> None:
        """``global_bundle_adjust`` of the map with this closer's settings."""
        global_bundle_adjust(self.map, self.verifier.stereo_cam, self.backend, self.cfg.global_ba_iterations,
                             self.cfg.global_ba_min_obs)

    def write_stats(self, path: Path) -> Path:
        """``loops.json``: candidates, verified / corrected loops as (query kf, candidate kf), relocalisations,
        database size and memory -- the false-loop count of a run without loops is ``verified``."""
        d = dataclasses.asdict(self.stats)
        d.update(keyframes_in_database=len(self.db), database_bytes=self.db.memory_bytes(), descriptor=self.cfg.descriptor)
        from vslam.outputs import write_text

        return write_text(path, json.dumps(d, indent=1))

    # -- final trajectory ---------------------------------------------------------------
    # -- relocalisation ---------------------------------------------------------------
    def relocalise(self, tracker, feats: Features, ur: np.ndarray, image: np.ndarray | None = None):
        """Tracking was lost: try the keyframes most similar to this frame. -> TrackResult | None."""
        if not len(self.db) or len(feats) < 10:
            return None
        vec = self.descriptor.describe(image, feats)
        tree = cKDTree(feats.uv)
        for c, _ in self.db.query(vec, self.cfg.reloc_top_k, min_score=self.cfg.min_score):
            res = tracker.track_keyframe(feats, ur, c, tree, "relocalised")
            if res is not None and res.ok:
                self.stats.relocalised += 1
                return res
        return None


def global_bundle_adjust(m: Map, stereo_cam: StereoCamera, backend: BackendConfig, iterations: int = 10,
                         min_obs: int = 20) -> None:
    """BA over every keyframe and point (first keyframe fixed, and those seeing fewer than ``min_obs`` points
    unless a ``PoseLink`` holds them) with the back end's local-BA machinery: after a loop correction or a map
    merge moved keyframes rigidly with their points, BA re-fits both to the observations, including the ones
    fused across the loop or the seam. Outlier observations are removed as in local BA."""
    pts = np.array(sorted(m.points), np.int64)
    okf, opt, ouv, our = [], [], [], []
    for pid in pts.tolist():
        for k, kp in m.points[pid].observations.items():
            f = m.keyframes[k]
            okf.append(k), opt.append(pid), ouv.append(f.features.uv[kp]), our.append(f.ur[kp])
    if not okf:
        return
    n_obs = np.bincount(np.array(okf), minlength=max(m.keyframes) + 1)
    linked = {k for ln in m.links for k in (ln.a, ln.b)}  # a dense-step keyframe is held by its links instead
    fixed = {min(m.keyframes)} | {k for k in m.keyframes if n_obs[k] < min_obs and k not in linked}
    problem = BAProblem({k: f.T_world_cam for k, f in m.keyframes.items()}, fixed,
                        {p: m.points[p].xyz for p in pts.tolist()}, np.array(okf), np.array(opt),
                        np.array(ouv).reshape(-1, 2), np.array(our, dtype=np.float64), links=list(m.links) or None)
    res = local_bundle_adjustment(problem, stereo_cam, dataclasses.replace(backend, max_iterations=iterations))
    m.apply_adjustment(res.poses, res.points, res.inliers, okf, opt, fixed)
    log.debug("global BA: %d keyframes, %d observations, %.0f ms", len(m.keyframes), len(okf), res.ms["total"])


def attach_saved_map(slam, path: str) -> None:
    """Load a saved map into a freshly built ``SlamTracker`` (map, tracker, mapper, loop closer, database)."""
    from vslam.loop.mapio import MapFileError, check_sensor, load_map, sensor_header

    loaded = load_map(path)
    check_sensor(path, loaded.header, sensor_header(slam.sensor, slam.cam, slam.cfg.features.extractor))
    slam.use_map(loaded.map)  # map files hold points only: a line map starts empty on the loaded keyframes
    if loaded.database.dim != slam.loop.db.dim:
        raise MapFileError(f"{path}: place descriptors of dimension {loaded.database.dim}, this config uses "
                           f"{slam.loop.db.dim} (slam.loop.descriptor)")
    slam.loop.db = loaded.database
    slam.map_id = loaded.current
    if loaded.others:
        if slam.atlas is not None:  # the run's other maps: new keyframes may merge into them
            if slam.atlas.descriptor is None:
                slam.atlas.descriptor = slam.loop.descriptor
            for mid, (om, odb) in loaded.others.items():
                slam.atlas.archive(mid, om, odb)
            slam.atlas.n_maps = max([loaded.current, *loaded.others]) + 1
        else:
            log.warning("%s: %d other maps in the file are not used (slam.atlas is off)", path, len(loaded.others))
    log.info("loaded map %s: %s", path, loaded.map.stats())


def save_slam_map(slam, path) -> Path:
    """Write a ``SlamTracker``'s maps (the current one and those its Atlas archived) with the place descriptor
    of every keyframe (computed if missing)."""
    from vslam.loop.mapio import save_map, sensor_header

    desc = slam.loop.descriptor if slam.loop is not None else make_place_descriptor(slam.cfg.loop.descriptor, slam.cfg.loop.vocabulary, slam.cfg.loop.weights)
    db = KeyframeDatabase(desc.dim)
    if slam.loop is not None:
        for k in slam.loop.db.ids().tolist():
            db.add(k, slam.loop.db.vector(k))
    others = dict(slam.atlas.maps) if slam.atlas is not None else {}
    for mid, om in others.items():
        odb = slam.atlas.dbs.get(mid)
        if odb is not None and odb.dim == db.dim:
            for k in odb.ids().tolist():
                db.add(k, odb.vector(k))
    for m in [slam.map, *others.values()]:
        for kf in m.keyframes.values():
            if kf.id not in db:
                db.add(kf.id, desc.describe(None, kf.features))
    return save_map(path, slam.map, db, slam.cfg.loop.descriptor,
                    sensor=sensor_header(slam.sensor, slam.cam, slam.cfg.features.extractor),
                    others=others, current=slam.map_id)
