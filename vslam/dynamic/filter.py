"""DynamicFilter: the one object SlamTracker talks to. Which keypoints of a frame may be tracked and mapped."""

from __future__ import annotations

import logging
from collections import deque
from pathlib import Path

import cv2
import numpy as np

from vslam.data.types import Frame, PinholeCamera
from vslam.dynamic.config import DynamicConfig
from vslam.dynamic.masking import Instances, box_iou, crop_mask, dilate, grow_in_box, in_boxes, in_mask, paint
from vslam.dynamic.motion import GeometricCheck
from vslam.features.base import Features
from vslam.features.matching import match_by_projection

log = logging.getLogger(__name__)

_SEGMENT_SAMPLES = 9  # points along a line segment tested like keypoints (``keep_segments``)


class DynamicFilter:
    """Per frame: ``keep(frame, features)`` before tracking (masks/boxes of dynamic objects -- a detection's
    instance mask where it has one, ``mask`` -- and the regions the geometric check flagged in the previous
    frame), then ``observe(T_world_cam)`` once the pose is tracked (geometric check; returns the kept keypoints
    that turned out to move, to be left out of mapping).

    With ``geometric.keep_static_boxes`` the check also judges each detector box of the frame from its own
    keypoints; boxes of the next frame that overlap one judged static are not masked (DynaSLAM keeps a sitting
    person's points only by luck of its region growing; here the verdict is per object and renewed every frame)."""

    def __init__(self, cfg: DynamicConfig, cam: PinholeCamera, detector: object | None = None,
                 extra: list[object] | None = None):
        self.cfg, self.cam = cfg, cam
        self.geo = GeometricCheck(cfg.geometric, cam) if cfg.geometric.enabled else None
        self.detector = detector
        if cfg.source == "detector" and detector is None:
            from vslam.dynamic.detector import default_weights

            self.detector = self._load(cfg.weights or default_weights(), "weights")
        # ``extra_weights``: detectors whose detections are unioned with the first one's (``extra``: already loaded)
        if extra is None:
            extra = [self._load(p, "extra_weights") for p in cfg.extra_weights] if cfg.source == "detector" else []
        self.extra = list(extra)
        # (timestamp, detections, those of them the box memory holds) of this and recent frames
        self._recent: deque[tuple[float, Instances, Instances]] = deque()
        self._objects = Instances.from_boxes(np.zeros((0, 4)))  # this frame's detections
        self._static = np.zeros((0, 4))  # boxes of the last checked frame judged static
        # (time, boxes) of the verdicts within the box memory: a box the memory holds keeps its verdict too
        self._static_held: deque[tuple[float, np.ndarray]] = deque()
        self._movers: list[tuple[float, np.ndarray]] = []  # (time, box) of objects seen moving, followed by overlap
        self._t = 0.0
        self._feats: Features | None = None
        self._depth = np.zeros(0)
        self._kept = np.zeros(0, bool)
        self._region_mask: np.ndarray | None = None  # this frame's dynamic regions (``dynamic_source``): pixels,
        self._region_boxes = np.zeros((0, 4))  # and boxes masked whole
        self._region_grow = 0.0
        self._span: tuple[tuple[int, float], np.ndarray] | None = None  # (frame key, ``_depth_span``)
        self._tracks: list[tuple[float, np.ndarray]] = []  # (time last detected, box now) (``box_track_s``)
        self._prev: Features | None = None  # the previous frame's keypoints, all of them

    def _load(self, path: str | Path, field_name: str) -> object:
        from vslam.nn.device import pick_device
        from vslam.dynamic.detector import load_detector

        det = load_detector(path, conf=self.cfg.score_threshold, field=f"slam.dynamic.{field_name}",
                            device=pick_device(self.cfg.device, "slam.dynamic.device"))
        if self.cfg.img_size:  # wide frames (KITTI 1226x370): people stay large enough at a larger input
            det.img_size = self.cfg.img_size
        if hasattr(det, "wide"):  # a YOLOX-style detector: square input unless the config keeps the aspect
            det.wide = self.cfg.wide
        return det

    def detect(self, frame: Frame) -> Instances | None:
        """Detections of the configured classes at ``score_threshold``, each with its instance mask cropped to
        its box where ``mask=instance`` and the network gave a mask that fills ``mask_min_fill`` of the box
        (``source=detector``; None otherwise, and on the frames ``detect_every`` skips).

        The image and its index alone decide them and nothing here is stateful, so one other thread may run this
        ahead of ``keep`` (the SLAM front end's prefetch thread does: the network then costs tracking nothing)."""
        c = self.cfg
        if c.source != "detector" or frame.index % c.detect_every:
            return None
        parts = []
        for network in [self.detector, *self.extra]:
            det = network.detect(frame.image)  # type: ignore[union-attr]
            sel = np.flatnonzero((det.scores >= c.score_threshold) & np.isin(det.class_names, list(c.classes)))
            boxes = det.boxes[sel].reshape(-1, 4)
            masks = getattr(det, "masks", None)
            if c.mask == "instance" and masks is not None:
                grow = int(np.ceil(c.mask_grow_cells * float(getattr(det, "mask_px", 0.0))))
                crops = tuple(crop_mask(grow_in_box(masks[k], b, grow), b, c.mask_min_fill) for k, b in zip(sel, boxes))
                parts.append(Instances(boxes, crops))
            else:
                parts.append(Instances.from_boxes(boxes))
        return Instances.concat(parts)

    def dynamic_source(self, frame: Frame, feats: Features, objects: Instances | None = None) -> np.ndarray:
        """(N,) bool: keypoints on dynamic objects according to ``cfg.source`` (dilated by ``dilation_px``);
        ``objects``: this frame's ``detect`` if computed ahead. Sets this frame's regions (``_on_dynamic``)."""
        c = self.cfg
        self._region_mask, self._region_boxes, self._region_grow = None, np.zeros((0, 4)), 0.0
        if c.source == "gt_mask":
            if frame.dynamic_mask is not None:
                self._region_mask = dilate(frame.dynamic_mask, c.dilation_px)
            elif frame.boxes is not None:
                self._region_boxes = np.asarray(frame.boxes, dtype=np.float64).reshape(-1, 4)
        elif c.source == "detector":
            fresh = self.detect(frame) if objects is None else objects
            if fresh is not None:  # else a frame between detections: the last detection's boxes hold
                self._objects = fresh
            self._t = frame.timestamp
            while self._recent and frame.timestamp - self._recent[0][0] > c.box_memory_s + 1e-6:
                self._recent.popleft()
            held = [kept for _, _, kept in self._recent]  # the window's objects, those confirmed when seen
            if fresh is not None:
                kept = self._confirmed(fresh, [seen.boxes for _, seen, _ in self._recent])
                self._recent.append((frame.timestamp, fresh, kept))
            else:  # the held detection is no new sighting (``detect_every``)
                kept = self._recent[-1][2] if self._recent else self._objects
                self._recent.append((frame.timestamp, Instances.from_boxes(np.zeros((0, 4))), kept))
            followed = Instances.from_boxes(self._follow(feats, frame.timestamp))
            objs = Instances.concat(held + [self._objects, followed])
            while self._static_held and frame.timestamp - self._static_held[0][0] > c.box_memory_s + 1e-6:
                self._static_held.popleft()
            static = np.vstack([self._static, *(b for _, b in self._static_held)]).reshape(-1, 4)
            if len(static) and len(objs):  # a static verdict unmasks the instance, box or mask
                objs = objs.subset(box_iou(objs.boxes, static).max(axis=1) < 0.5)
            whole = np.array([m is None for m in objs.masks], bool)
            self._region_boxes, self._region_grow = objs.boxes[whole], c.box_grow
            if not whole.all():  # the memory window's masks, one union
                shape = frame.image.shape[:2]
                self._region_mask = dilate(paint([m for m in objs.masks if m is not None], shape), c.dilation_px)
        return self._on_dynamic(feats.raw)

    def _confirmed(self, objs: Instances, window: list[np.ndarray]) -> Instances:
        """The detections of ``objs`` the box memory may hold: those seen in ``box_memory_min_hits`` frames of the
        window counting this one (a box overlapping, IoU >= 0.3, one of each earlier frame's boxes)."""
        need = self.cfg.box_memory_min_hits - 1
        if need <= 0 or not len(objs):
            return objs
        hits = np.zeros(len(objs), np.int64)
        for boxes in window:
            if len(boxes):
                hits += box_iou(objs.boxes, boxes).max(axis=1) >= 0.3
        return objs.subset(hits >= need)

    def _follow(self, feats: Features, t: float) -> np.ndarray:
        """(K,4) boxes of objects the detector found within ``box_track_s`` but not in this frame, moved with them:
        each by the median displacement of the keypoints matched into this frame from inside it in the previous
        one (raw pixels, ORB-SLAM-style guided matching within 40 px)."""
        c = self.cfg
        if c.box_track_s <= 0:
            return np.zeros((0, 4))
        fresh = self._objects.boxes
        out: list[tuple[float, np.ndarray]] = []
        for seen, box in self._tracks:
            if t - seen > c.box_track_s + 1e-6 or (len(fresh) and box_iou(box[None], fresh).max() >= 0.3):
                continue
            prev = self._prev
            if prev is not None and len(prev) and len(feats):
                inside = np.flatnonzero(in_boxes(prev.raw, box[None]))
                pairs = match_by_projection(prev.raw[inside], prev.desc[inside], feats.raw, feats.desc, 40.0,
                                            ratio=0.8)
                if len(pairs) >= c.box_track_min_matches:
                    d = np.median(feats.raw[pairs[:, 1]] - prev.raw[inside[pairs[:, 0]]], axis=0)
                    box = box + np.r_[d, d]
            w, h = self.cam.width, self.cam.height
            clipped = np.clip(box, [0, 0, 0, 0], [w, h, w, h])
            if (clipped[2] - clipped[0]) * (clipped[3] - clipped[1]) > 0.25 * (box[2] - box[0]) * (box[3] - box[1]):
                out.append((seen, box))  # gone when most of it has left the image
        followed = np.array([b for _, b in out]).reshape(-1, 4)
        self._tracks = out + [(t, b) for b in fresh]
        self._prev = feats
        return followed

    def _on_dynamic(self, raw_uv: np.ndarray) -> np.ndarray:
        """(N,) bool: raw pixels inside this frame's dynamic masks or boxes (as set by ``dynamic_source``)."""
        dyn = in_boxes(raw_uv, self._region_boxes, self.cfg.dilation_px, self._region_grow)
        if self._region_mask is not None:
            dyn |= in_mask(raw_uv, self._region_mask)
        return dyn

    def keep_segments(self, frame: Frame, raw: np.ndarray, ideal: np.ndarray) -> np.ndarray:
        """(L,) bool over line segments (raw and ideal (L,4) end points) of the frame last given to ``keep``: False
        for a segment whose samples all lie on a dynamic object (masks/boxes, and the geometric check's regions),
        which is then neither tracked nor mapped. All, not most: a person's own edges lie inside its box, while a
        static edge that the person occludes ends at the silhouette and one crossing the background of a loose
        box runs on outside it; "most" loses the static lines near people (docs/dynamic.md, 'Measurements behind
        settings in the code')."""
        raw = np.asarray(raw, dtype=np.float64).reshape(-1, 4)
        n = len(raw)
        if n == 0:
            return np.ones(0, bool)
        t = np.linspace(0.0, 1.0, _SEGMENT_SAMPLES)[None, :, None]

        def samples(segs: np.ndarray) -> np.ndarray:
            segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
            return (segs[:, None, :2] * (1.0 - t) + segs[:, None, 2:] * t).reshape(-1, 2)

        pr = samples(raw)
        dyn = self._on_dynamic(pr)
        if self.geo is not None and self.cfg.geometric.flag_points:
            dyn |= self.geo.in_region(samples(ideal), self._check_depth(frame, pr))
        return ~dyn.reshape(n, -1).all(axis=1)

    def keep(self, frame: Frame, feats: Features, objects: Instances | None = None) -> np.ndarray:
        """(N,) bool over ``feats``: True for keypoints that may be used for tracking and mapping; ``objects``:
        this frame's ``detect`` if computed ahead (else it runs here)."""
        dyn = self.dynamic_source(frame, feats, objects)
        self._feats = feats
        self._depth = self._check_depth(frame, feats.raw)
        if self.geo is not None and self.cfg.geometric.flag_points:
            dyn |= self.geo.in_region(feats.uv, self._depth)
        self._kept = ~dyn
        return self._kept.copy()

    def observe(self, T_world_cam: np.ndarray, tracked: bool = True) -> np.ndarray:
        """After tracking the frame given to ``keep``: (M,) bool over its kept keypoints, True where the geometric
        check flags motion. An untracked frame resets the check (its pose is only a prediction)."""
        n_kept = int(self._kept.sum())
        if self.geo is None or self._feats is None:
            return np.zeros(n_kept, bool)
        if not tracked:
            self.geo.reset()
            self._static, self._movers = np.zeros((0, 4)), []
            self._static_held.clear()
            return np.zeros(n_kept, bool)
        flagged = self.geo.check(T_world_cam, self._feats.uv, self._depth, self._feats.desc)
        if self.cfg.geometric.keep_static_boxes:
            self._static = self._static_boxes(self._feats, self.geo)
            if len(self._static):
                self._static_held.append((self._t, self._static))
        if not self.cfg.geometric.flag_points:  # the check judged the boxes only
            return np.zeros(n_kept, bool)
        return flagged[self._kept]

    @property
    def static_boxes(self) -> np.ndarray:
        """(K,4) detector boxes of the last checked frame judged static (``geometric.keep_static_boxes``)."""
        return self._static.copy()

    def _static_boxes(self, feats: Features, geo: GeometricCheck) -> np.ndarray:
        """This frame's detector boxes whose object shows (almost) no motion and was not seen moving within
        ``moving_memory_s`` (a box overlapping, IoU >= 0.3, a box of a moving object carries that object on: a
        walker slows to a stop at every turn). The object is the box's front: compared keypoints within
        ``region_depth_m`` behind the ``static_min_points``-th nearest of them (a walker's box can hold more
        static background than walker, which would outvote it)."""
        g, out = self.cfg.geometric, []
        self._movers = [(t, b) for t, b in self._movers if self._t - t <= g.moving_memory_s + 1e-6]
        for box in self._objects.boxes:
            inside = in_boxes(feats.raw, box[None], self.cfg.dilation_px, self.cfg.box_grow) & geo.tested
            judged = moving = False  # too few compared keypoints: neither verdict
            if inside.sum() >= g.static_min_points:
                near = np.sort(self._depth[inside])[g.static_min_points - 1]
                front = inside & (self._depth <= near + g.region_depth_m)
                judged, moving = True, int((front & geo.seeds).sum()) > g.static_max_moving * int(front.sum())
            known = np.array([b for _, b in self._movers]).reshape(-1, 4)
            if moving or (len(known) and box_iou(box[None], known).max() >= 0.3):
                self._movers.append((self._t, box))
            elif judged:
                out.append(box)
        return np.array(out, np.float64).reshape(-1, 4)

    def _check_depth(self, frame: Frame, raw_uv: np.ndarray) -> np.ndarray:
        """(N,) metres at raw pixels (keypoints, segment samples) from the frame's depth map (RGB-D); NaN without
        one (the geometric check then has nothing to compare, stereo/mono are not covered yet) and, with
        ``geometric.edge_m``, on depth edges."""
        if frame.depth is None or self.geo is None:
            return np.full(len(raw_uv), np.nan)
        g = self.cfg.geometric
        z, r, c = self._depth_at(frame, raw_uv)
        if g.edge_m > 0:  # on a depth edge the keypoint's depth may be the background's
            span = self._depth_span(frame)
            z = np.where(span[r, c] <= g.edge_m + g.rel * z, z, np.nan)
        return z

    def _depth_span(self, frame: Frame) -> np.ndarray:
        """(H,W) max - min depth within 2 px of each pixel (holes, 0, left out: Kinect holes are everywhere); kept
        for the frame, which asks again for its line segments."""
        key = (frame.index, frame.timestamp)
        if self._span is None or self._span[0] != key:
            d = frame.depth.astype(np.float32)
            k = np.ones((5, 5), np.uint8)
            hi = cv2.dilate(d, k)  # holes raise neither bound
            lo = cv2.erode(np.where(d > 0, d, np.float32(1e6)), k)
            self._span = (key, hi - lo)
        return self._span[1]

    def _depth_at(self, frame: Frame, raw_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N,) metres of the frame's depth map at the rounded raw pixels, NaN outside the check's depth range;
        with the (N,) pixel rows and columns read."""
        g = self.cfg.geometric
        r = np.clip(np.rint(raw_uv[:, 1]).astype(int), 0, frame.depth.shape[0] - 1)
        c = np.clip(np.rint(raw_uv[:, 0]).astype(int), 0, frame.depth.shape[1] - 1)
        z = frame.depth[r, c].astype(np.float64)
        return np.where((z >= g.min_depth) & (z <= g.max_depth), z, np.nan), r, c
