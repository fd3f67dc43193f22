"""The run's maps, as ``SlamTracker`` keeps them: the recovery ladder of a frame (``_measure``), what a frame no
step measured does (predicted, a new map, an archived map taken up again), and maps merged where they meet
(``vslam.tracking.atlas`` holds the archived maps; docs/tracking.md, "Never lost", has the states as a diagram).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from vslam.data.types import Frame
from vslam.features import Features
from vslam.mapping.map import Map
from vslam.tracking.atlas import Atlas
from vslam.tracking.baseline import FrameEstimate
from vslam.tracking.mono_init import MonoInitializer
from vslam.tracking.tracker import TrackResult

log = logging.getLogger(__name__)


class MapRecovery:
    """``SlamTracker``'s tracking states and maps (a base class: the methods read and set the tracker's map,
    pose and reference keyframe)."""

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
        the reference keyframe by descriptor, after a loss or a wide gap the newest keyframes (``Tracker.track``);
        place relocalisation over the whole map (``slam.loop``); the dense depth step (RGB-D, ``slam.dense``); the
        archived maps (``_relocalise_archived``), one of which then becomes the current map again."""
        wide = self._t_tracked is not None and frame.timestamp - self._t_tracked >= self.cfg.tracking.wide_gap_s
        res = self.tracker.track(feats, ur, T_pred, self.ref_kf, after_loss=not self._prev_tracked,  # type: ignore[arg-type]
                                 last_ids=self._last_ids, wide=wide)
        for s in self.stages:  # place relocalisation of a lost frame; lines refine a tracked pose; dense depth
            res = s.measure(self, frame, feats, ur, T_pred, res)  # tracking tries a lost one
        if not res.ok:  # the camera may be back in a map it left: that map continues
            res = self._relocalise_archived(frame, feats, ur) or res
        return res

    def _without_map(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray,
                     est: FrameEstimate) -> None:
        """A frame while there is no current map: the first map or the next one starts here ("new_map"), or a
        monocular camera waiting for its two-view initialisation is relocalised in a map it left."""
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

    def _lost(self, frame: Frame, feats: Features, depth: np.ndarray, ur: np.ndarray, T_pred: np.ndarray,
              est: FrameEstimate) -> None:
        """A frame no recovery step measured: predicted (motion model) at first; once lost for
        ``atlas.new_map_after_s`` and ``atlas.min_lost_frames`` frames in a row (or right after a gap in the
        images) a new map from this frame if it can make one; past ``atlas.bridge_s`` no pose."""
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

    def _lost_for(self, t: float) -> float:
        """Seconds since the last tracked frame; 0 while a new map cannot be made (no Atlas)."""
        return 0.0 if self.atlas is None or self._t_tracked is None else t - self._t_tracked

    def use_map(self, m: Map) -> None:
        """Make ``m`` the map the tracker, the mapper and every stage work on (a map switch, a merge, a loaded
        map)."""
        self.map = self.tracker.map = self.mapper.map = self.frames.map = m
        self.mapper.recent = [p for p in self.mapper.recent if p in m.points]
        self._last_ids = None
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
        if self._archive_current():
            self.map_id = atlas.new_id()
        self._set_loop_database(None)
        self.use_map(self.map.successor())
        for s in self.stages:
            s.on_new_map()
        self.ref_kf, self.velocity, self._t_tracked = None, np.eye(4), None
        log.info("frame %d: tracking lost; map %d started", frame.index, self.map_id)
        if self.mono_init is None:
            return self._initialize(frame, feats, depth, ur, T0)
        self._fresh_mono_init()
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
        self._archive_current()
        self._set_loop_database(db)
        self.use_map(m)
        self.map_id = map_id
        self._restart = None
        if self.mono_init is not None:
            self._fresh_mono_init()
        atlas.switches += 1
        atlas.votes = []

    def _archive_current(self) -> bool:
        """Keep the current map (and the loop closer's database of it) in the Atlas -> False when it has no
        keyframe yet, and nothing was kept."""
        if not self.map.keyframes:
            return False
        self.atlas.archive(self.map_id, self.map, self.loop.db if self.loop is not None else None)  # type: ignore[union-attr]
        return True

    def _set_loop_database(self, db) -> None:
        """The loop closer's place database for the map that becomes current: ``db``, or an empty one."""
        if self.loop is None:
            return
        from vslam.loop.database import KeyframeDatabase

        self.loop.db = db if db is not None else KeyframeDatabase(self.loop.descriptor.dim)
        self.loop._groups = []

    def _fresh_mono_init(self) -> None:
        """Monocular: the two-view initialiser starts over (the frames it held belong to a map given up)."""
        self.mono_init = MonoInitializer(self.cam, self.cfg.init)
        self._pre_init = []

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
        """Look for the new keyframe in the archived maps (none: nothing to do); on a confirmed match move this map
        into that one."""
        atlas = self.atlas
        if atlas is None or not atlas.maps:
            return {}
        t = time.perf_counter()
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
            self.scale_motion(scale)
        old.absorb(new, T_old_new, scale)
        if self.loop is not None and old_db is not None:  # one database for the merged map
            for k in old_db.ids().tolist():
                self.loop.db.add(k, old_db.vector(k))
        self.use_map(old)
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
