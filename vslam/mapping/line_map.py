"""Line landmarks in the SLAM map, and the line steps of tracking and local mapping (seed 003 ch. 3).

``LineSlam`` is what ``SlamTracker`` calls when ``slam.lines.enabled``; everything line-specific lives
here so the point-only path is untouched when it is off:

- ``detect``: LSD segments + band descriptors of a frame (``features.lines``).
- ``track``: after the point tracker, project the local map's lines with its pose, match them
  (``match_lines``), and refine the pose on points + lines (``backend.pose_lines``).
- ``add_keyframe``: keep the keyframe's segments, attach the tracked line observations, create new lines
  from the RGB-D depth map (depth sampled along each unmatched segment on both sides of the edge, each side
  extrapolated to it, a 3-D line fitted to the samples and accepted when they lie on it) or, stereo, from the
  end-point depths the rig measured (the segment's match in the right image, ``stereo_inverse_depths``).
- ``triangulate`` (local mapping, monocular / stereo, or with ``create: both``): the new keyframe's unmatched
  segments matched to its covisible keyframes' unmatched segments by descriptor + epipolar overlap
  (``features.lines.match_epipolar_segments``), the two back-projected planes intersected
  (``geometry.plucker.triangulate_planes``), kept when the planes meet at a usable angle and the line lies
  in front of both cameras. Such a line must be seen again (``two_view_min_obs``) or it is culled.
- ``ba_problem`` / ``apply_ba``: the window's lines for local BA (``backend.line_ba``) and the results back.
- ``write_ply``: the map lines as an open3d ``LineSet`` PLY (end points = extent seen by the first view).

"""

from __future__ import annotations

import errno
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vslam.backend.line_ba import LineProblem
from vslam.backend.pose_lines import refine_pose_points_lines
from vslam.data.types import PinholeCamera, SensorKind
from vslam.features.lines import LineConfig, LineExtractor, LineFeatures, match_epipolar_segments, match_lines
from vslam.geometry import plucker as pl
from vslam.geometry.se3 import inv_T
from vslam.geometry.triangulation import fundamental

log = logging.getLogger(__name__)


@dataclass
class MapLine:
    """A 3-D line: L (6,) Plücker world (|d| = 1); ends (2,3) world extent, oriented like the segments;
    desc (D,) band descriptor; observations {kf_id: segment index}; first_kf: creating keyframe."""

    id: int
    L: np.ndarray
    ends: np.ndarray
    desc: np.ndarray
    first_kf: int
    observations: dict[int, int] = field(default_factory=dict)
    two_view: bool = False  # triangulated from two keyframes (held to ``two_view_min_obs``), not from depth


class LineMap:
    """Line landmarks and each keyframe's segments; single-threaded, ids increase from 0."""

    def __init__(self) -> None:
        self.lines: dict[int, MapLine] = {}
        self.kf_feats: dict[int, LineFeatures] = {}
        self.kf_ids: dict[int, np.ndarray] = {}  # kf id -> (N,) line id per segment, -1 none
        self._next = 0

    def add_line(self, L: np.ndarray, ends: np.ndarray, kf_id: int, idx: int) -> MapLine:
        ml = MapLine(self._next, pl.normalize(L), np.asarray(ends, dtype=np.float64), self.kf_feats[kf_id].desc[idx].copy(), kf_id)
        self.lines[ml.id] = ml
        self._next += 1
        self.add_observation(ml.id, kf_id, idx)
        return ml

    def add_observation(self, lid: int, kf_id: int, idx: int) -> None:
        ids = self.kf_ids[kf_id]
        if ids[idx] >= 0 or kf_id in self.lines[lid].observations:
            return
        self.lines[lid].observations[kf_id] = int(idx)
        ids[idx] = lid

    def remove_observation(self, lid: int, kf_id: int) -> None:
        ml = self.lines.get(lid)
        if ml is None or kf_id not in ml.observations:
            return
        idx = ml.observations.pop(kf_id)
        if self.kf_ids[kf_id][idx] == lid:
            self.kf_ids[kf_id][idx] = -1
        if not ml.observations:
            del self.lines[lid]

    def remove_line(self, lid: int) -> None:
        for k in list(self.lines[lid].observations):
            self.remove_observation(lid, k)

    def seen_by(self, kf_ids: list[int]) -> np.ndarray:
        """Sorted unique ids of the lines observed by any of ``kf_ids``."""
        arr = [self.kf_ids[k] for k in kf_ids if k in self.kf_ids]
        if not arr:
            return np.zeros(0, np.int64)
        u = np.unique(np.concatenate(arr))
        return u[u >= 0]


def project_segments(ends: np.ndarray, T_world_cam: np.ndarray, cam: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(P,2,3) world end points -> (P,4) ideal-pixel segments and (P,) mask: both ends in front (> 0.1 m)
    and the segment at least partly inside the image."""
    Tcw = inv_T(T_world_cam)
    pc = ends @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([cam.fx * pc[..., 0] / z + cam.cx, cam.fy * pc[..., 1] / z + cam.cy], axis=-1)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] < cam.height)
    ok = (z > 0.1).all(axis=1) & inside.any(axis=1)
    return uv.reshape(-1, 4), ok


def moved_line(L: np.ndarray, ends: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Line (6,) and its end points (2,3) under x <- D x, D (4,4) = [s R | t]: two points of the line moved and
    joined again (orientation kept), |d| = 1."""
    p0 = pl.closest_point(pl.normalize(L))
    pts = np.stack([p0, p0 + pl.normalize(L)[3:], *ends]) @ D[:3, :3].T + D[:3, 3]
    return pl.normalize(pl.from_points(pts[0], pts[1])), pts[2:]


def _bilinear(img: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Bilinear samples of a depth map at pixel positions p (...,2) (x, y); NaN where a corner has no depth."""
    h, w = img.shape[:2]
    x = np.clip(p[..., 0], 0, w - 1.001)
    y = np.clip(p[..., 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    c = [img[y0 + j, x0 + i].astype(np.float64) for j in (0, 1) for i in (0, 1)]
    z = (c[0] * (1 - fx) + c[1] * fx) * (1 - fy) + (c[2] * (1 - fx) + c[3] * fx) * fy
    with np.errstate(invalid="ignore"):
        bad = np.any([~(ci > 0) for ci in c], axis=0)
    return np.where(bad, np.nan, z)


class LineSlam:
    """The line half of the SLAM system; see the module docstring."""

    def __init__(self, slam_map, cam: PinholeCamera, stereo_cam, sensor: SensorKind, cfg: LineConfig, backend,
                 calibration=None):
        self.map, self.cam, self.stereo_cam, self.sensor, self.cfg, self.backend = slam_map, cam, stereo_cam, sensor, cfg, backend
        self.lmap = LineMap()
        self.extractor = LineExtractor(cfg)
        self.K_L = pl.line_projection_matrix(cam.fx, cam.fy, cam.cx, cam.cy)
        # whitening of an end point's inverse-depth residual: fx b / sigma, a disparity (RGB-D: the virtual
        # baseline of the points' depth; stereo: the rig's) -- 0: lines are image-only
        sigma = {"rgbd": cfg.depth_sigma_px, "stereo": cfg.stereo_depth_sigma_px}.get(sensor, 0.0)
        rig = sensor != "stereo" or (calibration is not None and calibration.cam1 is not None
                                     and calibration.T_cam0_cam1 is not None)
        self.depth_weight = stereo_cam.fx * stereo_cam.baseline / sigma if sigma > 0 and stereo_cam.baseline > 0 and rig else 0.0
        # "depth": the RGB-D depth map, or the stereo rig's measured end-point depths (``stereo_inverse_depths``)
        measured = sensor == "rgbd" or (sensor == "stereo" and self.depth_weight > 0)
        auto = {"rgbd": "depth", "stereo": "both"}.get(sensor, "two_view") if measured else "two_view"
        create = auto if cfg.create == "auto" else cfg.create
        if create in ("depth", "both") and not measured:
            log.warning("lines: create=%s needs an RGB-D depth map or a stereo rig with stereo_depth_sigma_px > 0; "
                        "%s lines come from two views", create, sensor)
            create = "two_view"
        self.from_depth, self.from_two_views = create in ("depth", "both"), create in ("two_view", "both")
        self.cam1 = calibration.cam1 if sensor == "stereo" and self.depth_weight > 0 else None
        if self.cam1 is not None:  # the rig, once: right pixels in the left camera's units, F, the matcher's gate
            self.T_c0_c1 = np.asarray(calibration.T_cam0_cam1, dtype=np.float64)
            self._H_right = cam.K @ np.linalg.inv(self.cam1.K)  # the planes depend on normalised coordinates only
            self._F_rig = fundamental(np.eye(4), self.T_c0_c1, cam.K)
            self._stereo_match_cfg = replace(cfg, tri_min_epi_angle_deg=cfg.stereo_min_epi_angle_deg)

    def detect(self, image: np.ndarray, depth_map: np.ndarray | None = None, right: np.ndarray | None = None
               ) -> LineFeatures:
        """Segments of the image; with an RGB-D depth map (``depth_sigma_px``) or the stereo rig's right image
        (``stereo_depth_sigma_px``) their end points' depths."""
        lf = self.extractor.detect(image, self.cam)
        if self.depth_weight > 0 and len(lf):
            if depth_map is not None:
                lf.rho = self.end_inverse_depths(lf, depth_map)
            elif right is not None and self.cam1 is not None:
                lf.rho = self.stereo_inverse_depths(lf, self.extractor.detect(right, self.cam1))
        return lf

    def stereo_inverse_depths(self, lf: LineFeatures, rf: LineFeatures) -> np.ndarray:
        """(N,2) inverse depths of the left segments' end points from their matches among the right image's
        segments ``rf``: the two back-projected planes meet in the 3-D line (left camera frame); NaN unmatched."""
        if len(rf) == 0:
            return np.full((len(lf), 2), np.nan)
        rs = np.hstack([rf.segs.reshape(-1, 2), np.ones((2 * len(rf), 1))]) @ self._H_right.T
        rsegs = (rs[:, :2] / rs[:, 2:]).reshape(-1, 4)
        m = match_epipolar_segments(lf.segs, lf.desc, rsegs, rf.desc, self._F_rig, self._stereo_match_cfg)
        Lc = np.full((len(lf), 6), np.nan)
        if len(m):
            Lc[m[:, 0]] = pl.triangulate_planes(lf.segs[m[:, 0]], rsegs[m[:, 1]], np.eye(4), self.T_c0_c1, self.cam.K)[0]
        return self._end_rho(Lc, lf.segs)

    def end_inverse_depths(self, lf: LineFeatures, depth_map: np.ndarray) -> np.ndarray:
        """(N,2) inverse depths of the segments' end points measured by the 3-D line their depth samples fit
        (``fit_from_depth`` in the camera frame), NaN where they fit none."""
        return self._end_rho(self.fit_from_depth(lf.raw, lf.segs, depth_map, np.eye(4), extrapolate=True)[1], lf.segs)

    def _end_rho(self, Lc: np.ndarray, segs: np.ndarray) -> np.ndarray:
        """(N,2) inverse depths of camera-frame lines Lc (N,6; NaN rows: none) at the end-point rays of segs;
        NaN where a line has none there or lies behind the camera."""
        rho = np.full((len(Lc), 2), np.nan)
        ok = np.isfinite(Lc).all(axis=1)
        if ok.any():
            r = pl.inverse_depth(Lc[ok, :3], Lc[ok, 3:], pl.end_rays(segs[ok], self.K_L))[0]
            rho[ok] = np.where(r > 0, r, np.nan)
        return rho

    # -- tracking -------------------------------------------------------------------------------------------
    def local_lines(self, ref_kf: int, local_keyframes: int) -> np.ndarray:
        kfs, _ = self.map.local_map(ref_kf, local_keyframes)
        return self.lmap.seen_by(kfs)

    def match(self, T_world_cam: np.ndarray, lf: LineFeatures, lids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projection matching of map lines ``lids`` into segments ``lf`` -> (matched line ids, segment indices)."""
        if len(lids) == 0 or len(lf) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        ends = np.array([self.lmap.lines[int(i)].ends for i in lids])
        pred, vis = project_segments(ends, T_world_cam, self.cam)
        idx = np.flatnonzero(vis)
        if len(idx) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        desc = np.array([self.lmap.lines[int(i)].desc for i in lids[idx]]).reshape(len(idx), -1)
        m = match_lines(pred[idx], desc, lf, self.cfg)
        return lids[idx[m[:, 0]]], m[:, 1]

    def track(self, T_world_cam: np.ndarray, point_xyz: np.ndarray, point_uv: np.ndarray, point_ur: np.ndarray,
              lf: LineFeatures, ref_kf: int, local_keyframes: int) -> tuple[np.ndarray, np.ndarray]:
        """Refine the tracked pose with the point inliers and the matched lines.

        -> (T_world_cam, line id per segment of ``lf`` (-1: none or outlier)).
        """
        line_ids = np.full(len(lf), -1, np.int64)
        lids, segi = self.match(T_world_cam, lf, self.local_lines(ref_kf, local_keyframes))
        if len(lids) == 0:
            return T_world_cam, line_ids
        L = np.array([self.lmap.lines[int(i)].L for i in lids])
        rho = None if lf.rho is None else lf.rho[segi]  # measured only with depth_weight > 0 (``detect``)
        T, _, lin = refine_pose_points_lines(T_world_cam, point_xyz, point_uv, point_ur, L, lf.segs[segi], self.K_L,
                                             self.stereo_cam, self.backend, self.cfg.pixel_sigma, self.cfg.weight,
                                             rho, self.depth_weight)
        line_ids[segi[lin]] = lids[lin]
        return T, line_ids

    def refine_tracked(self, T_world_cam: np.ndarray, point_ids: np.ndarray, feats, ur: np.ndarray, lf: LineFeatures | None,
                       ref_kf: int, local_keyframes: int) -> tuple[np.ndarray, np.ndarray | None]:
        """``track`` from the point tracker's result: point_ids (N,) map point per keypoint (-1 none)."""
        if lf is None:
            return T_world_cam, None
        kp = np.flatnonzero(point_ids >= 0)
        xyz = self.map.points_xyz(point_ids[kp])
        return self.track(T_world_cam, xyz, feats.uv[kp], ur[kp], lf, ref_kf, local_keyframes)

    # -- mapping --------------------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, T_world_cam: np.ndarray, lf: LineFeatures, line_ids: np.ndarray | None,
                     depth_map: np.ndarray | None) -> int:
        """Store the keyframe's segments, attach tracked observations, create lines from depth. -> new lines."""
        self.cull(kf_id)
        self.lmap.kf_feats[kf_id] = lf
        self.lmap.kf_ids[kf_id] = np.full(len(lf), -1, np.int64)
        if line_ids is not None:
            for i in np.flatnonzero(line_ids >= 0):
                if int(line_ids[i]) in self.lmap.lines:
                    self.lmap.add_observation(int(line_ids[i]), kf_id, int(i))
        if not self.from_depth or len(lf) == 0 or (depth_map is None and lf.rho is None):  # nothing measured
            return 0
        free = np.flatnonzero(self.lmap.kf_ids[kf_id] < 0)
        free = free[np.argsort(-lf.length[free], kind="stable")]
        if depth_map is not None:
            ok, L, ends = self.fit_from_depth(lf.raw[free], lf.segs[free], depth_map, T_world_cam, extrapolate=self.cfg.create_extrapolate)
        else:
            ok, L, ends = self.from_rig(lf.segs[free], lf.rho[free], T_world_cam)
        n = 0
        for j in np.flatnonzero(ok)[: self.cfg.max_new_lines].tolist():  # the longest segments that fit
            self.lmap.add_line(L[j], ends[j], kf_id, int(free[j]))
            n += 1
        return n

    def from_rig(self, seg: np.ndarray, rho: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """3-D lines of stereo segments (S,4) whose end points the rig measured (rho (S,2) inverse depths,
        ``stereo_inverse_depths``) -> (ok (S,), L (S,6), ends (S,2,3)) as ``fit_from_depth``; ok needs both end
        points at a disparity of at least ``rig_min_disparity_px`` (a far end point's depth is a guess)."""
        seg, rho = np.asarray(seg, dtype=np.float64).reshape(-1, 4), np.asarray(rho, dtype=np.float64).reshape(-1, 2)
        S = len(seg)
        out_ok, out_L, out_e = np.zeros(S, bool), np.full((S, 6), np.nan), np.full((S, 2, 3), np.nan)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.isfinite(rho) & (rho * self.stereo_cam.fx * self.stereo_cam.baseline >= self.cfg.rig_min_disparity_px), axis=1)
        if ok.any():
            a, b = pl.end_points_from_depth(seg[ok], 1.0 / rho[ok, 0], 1.0 / rho[ok, 1], T_world_cam, self.cam.K)
            out_L[ok] = pl.normalize(pl.from_points(a, b))
            out_e[ok] = np.stack([a, b], axis=1)
            out_ok = ok & np.isfinite(out_L).all(axis=1)
        return out_ok, out_L, out_e

    def fit_from_depth(self, raw: np.ndarray, seg: np.ndarray, depth_map: np.ndarray, T_world_cam: np.ndarray,
                       extrapolate: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """3-D lines of segments (S,4) (``raw`` pixels to sample depth, ``seg`` ideal ones) from depth sampled
        along them -> (ok (S,), L (S,6), ends (S,2,3)); not ok where the samples do not lie on one 3-D line (a
        depth edge, missing depth). Batched over the segments (one keyframe's ~100 were costly one by one in a loop)."""
        raw = np.asarray(raw, dtype=np.float64).reshape(-1, 4)
        seg = np.asarray(seg, dtype=np.float64).reshape(-1, 4)
        S = len(raw)
        out_ok, out_L, out_e = np.zeros(S, bool), np.full((S, 6), np.nan), np.full((S, 2, 3), np.nan)
        if S == 0:
            return out_ok, out_L, out_e
        h, w = depth_map.shape[:2]
        t = np.linspace(0.05, 0.95, 11)
        d = raw[:, 2:] - raw[:, :2]
        nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)[:, None]
        zs = []  # depth 2 px either side of the segment (and 4 px, for the contour test)
        for off in ((-2.0, 2.0, -4.0, 4.0) if self.cfg.reject_contours or extrapolate else (-2.0, 2.0)):
            p = raw[:, None, :2] + t[None, :, None] * d[:, None, :] + off * nrm[:, None, :]  # (S,11,2)
            if extrapolate:
                zs.append(_bilinear(depth_map, p))
            else:
                ix = np.clip(np.round(p).astype(np.int64), 0, [w - 1, h - 1])
                zs.append(depth_map[ix[..., 1], ix[..., 0]].astype(np.float64))
        # the nearer side; NaN only where both are missing. Their mean on one surface halves the creation error but
        # measured worse on the corridor seeds (docs/lines.md)
        if extrapolate:  # each side's depth extrapolated to the segment (2 z(2 px) - z(4 px)), both averaged
            with np.errstate(invalid="ignore"):
                ex = [np.where((a > 0) & (b > 0), 2 * a - b, np.nan) for a, b in ((zs[0], zs[2]), (zs[1], zs[3]))]
            z = np.where(np.isfinite(ex[0]) & np.isfinite(ex[1]), 0.5 * (ex[0] + ex[1]), np.fmin(ex[0], ex[1]))
        else:
            z = np.fmin(zs[0], zs[1])
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(z) & (z > 0.1) & (z < 10.0)
            if self.cfg.surface_only:  # both sides at one depth: a texture / crease edge, not an occluding contour
                ok &= np.abs(zs[0] - zs[1]) <= self.cfg.depth_fit_m + 0.02 * z
            if self.cfg.reject_contours:  # each side's surface extrapolated to the segment: a crease's meet there
                jump = np.abs((2 * zs[0] - zs[2]) - (2 * zs[1] - zs[3]))
                known = np.all([zi > 0 for zi in zs], axis=0)  # a side without depth (0 / NaN): not judged
                ok &= ~(known & (jump > self.cfg.depth_fit_m + 0.02 * z))
        cnt = ok.sum(axis=1)
        fit = cnt >= max(self.cfg.min_depth_samples, 2)
        if not fit.any():
            return out_ok, out_L, out_e
        ok, z, sg, cnt = ok[fit], np.where(ok[fit], z[fit], 0.0), seg[fit], cnt[fit]
        uv = sg[:, None, :2] + t[None, :, None] * (sg[:, None, 2:] - sg[:, None, :2])
        P = self.cam.backproject(uv.reshape(-1, 2), z.reshape(-1)).reshape(len(sg), len(t), 3)
        wgt = ok.astype(np.float64)[:, :, None]
        c = (P * wgt).sum(axis=1) / cnt[:, None]
        Q = (P - c[:, None, :]) * wgt
        u = np.linalg.eigh(np.einsum("sni,snj->sij", Q, Q))[1][:, :, -1]  # principal direction (SVD's first)
        dev = np.linalg.norm(Q - np.einsum("sn,si->sni", np.einsum("sni,si->sn", Q, u), u), axis=2)
        zmean = (z * ok).sum(axis=1) / cnt
        good = dev.max(axis=1) <= self.cfg.depth_fit_m + 0.01 * zmean
        Lc = np.concatenate([np.cross(c, u), u], axis=1)
        Lw = pl.transform(Lc, T_world_cam)
        ea, eb = pl.clip_to_segment(Lw, sg, T_world_cam, self.cam.K)
        idx = np.flatnonzero(fit)[good]
        out_ok[idx] = True
        out_L[idx] = Lw[good]
        out_e[idx] = np.stack([ea, eb], axis=1)[good]
        return out_ok, out_L, out_e

    def triangulate(self, kf, neighbors: list[int]) -> int:
        """New lines from the keyframe's unmatched segments and each neighbour's (most covisible first), see
        the module docstring; at most ``max_new_lines``. -> lines created."""
        if not self.from_two_views or kf.id not in self.lmap.kf_feats:
            return 0
        lf, n = self.lmap.kf_feats[kf.id], 0
        for nb_id in neighbors:
            nf = self.lmap.kf_feats.get(nb_id)
            if nf is None or n >= self.cfg.max_new_lines:
                continue
            a = np.flatnonzero(self.lmap.kf_ids[kf.id] < 0)
            b = np.flatnonzero(self.lmap.kf_ids[nb_id] < 0)
            ia, ib, L, ends = self._two_view(lf, a, kf.T_world_cam, nf, b, self.map.keyframes[nb_id].T_world_cam)
            for j in range(min(len(ia), self.cfg.max_new_lines - n)):
                ml = self.lmap.add_line(L[j], ends[j], kf.id, int(ia[j]))
                ml.two_view = True
                self.lmap.add_observation(ml.id, nb_id, int(ib[j]))
                n += 1
        return n

    def _two_view(self, fa: LineFeatures, a: np.ndarray, T_a: np.ndarray, fb: LineFeatures, b: np.ndarray,
                  T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lines from segments ``a`` of keyframe a and ``b`` of keyframe b
        -> (indices into fa, into fb, world lines (M,6), end points (M,2,3) on a's segments), longest first:
        matched by ``match_epipolar_segments``, planes meeting at >= ``tri_min_angle_deg``, both end points in
        front of both cameras and seen from the two centres at >= ``tri_min_parallax_deg`` (a far end point
        leaves the line's direction to a pixel's guess, as a far point's depth)."""
        K = self.cam.K
        m = match_epipolar_segments(fa.segs[a], fa.desc[a], fb.segs[b], fb.desc[b], fundamental(T_a, T_b, K), self.cfg)
        ia, ib = a[m[:, 0]], b[m[:, 1]]
        L, sin = pl.triangulate_planes(fa.segs[ia], fb.segs[ib], T_a, T_b, K)
        ok = np.isfinite(L).all(axis=1) & (sin >= np.sin(np.radians(self.cfg.tri_min_angle_deg)))
        ea, eb = pl.clip_to_segment(L, fa.segs[ia], T_a, K)
        cos_min = np.cos(np.radians(self.cfg.tri_min_parallax_deg))
        for e in (ea, eb):
            for T in (T_a, T_b):
                Tcw = inv_T(T)
                ok &= (e @ Tcw[:3, :3].T + Tcw[:3, 3])[:, 2] > 0
            ra, rb = e - T_a[:3, 3], e - T_b[:3, 3]
            with np.errstate(invalid="ignore", divide="ignore"):
                ok &= np.sum(ra * rb, 1) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1)) <= cos_min
        keep = np.flatnonzero(ok)
        keep = keep[np.argsort(-fa.length[ia[keep]], kind="stable")]
        return ia[keep], ib[keep], L[keep], np.stack([ea[keep], eb[keep]], axis=1)

    def ba_problem(self, kf_ids: list[int]) -> LineProblem | None:
        """Lines seen by the BA's keyframes (at most ``ba_max_lines``, most observed first) with enough views
        among them (``LineConfig.ba_min_views``)."""
        lids = self.lmap.seen_by(kf_ids)
        kset = set(kf_ids)
        cand = [(len([k for k in self.lmap.lines[int(i)].observations if k in kset]), int(i)) for i in lids]
        views = self.cfg.ba_min_views or (3 if self.sensor == "mono" else 2)
        cand = sorted([c for c in cand if c[0] >= max(2, views)], key=lambda c: (-c[0], c[1]))[: self.cfg.ba_max_lines]
        if not cand:
            return None
        kf, ln, seg, rho = [], [], [], []
        nan2 = np.full(2, np.nan)
        for _, j in cand:
            for k, idx in self.lmap.lines[j].observations.items():
                if k in kset:
                    f = self.lmap.kf_feats[k]
                    kf.append(k), ln.append(j), seg.append(f.segs[idx]), rho.append(nan2 if f.rho is None else f.rho[idx])
        return LineProblem({j: self.lmap.lines[j].L for _, j in cand}, np.array(kf), np.array(ln), np.array(seg),
                           sigma=self.cfg.pixel_sigma, obs_rho=np.array(rho) if self.depth_weight > 0 else None,
                           depth_weight=self.depth_weight)

    def apply_ba(self, lp: LineProblem | None, lines: dict[int, np.ndarray], inliers: np.ndarray | None,
                 poses: dict[int, np.ndarray]) -> None:
        """Write BA's lines back (end points re-clipped to the first view) and drop outlier observations."""
        if lp is None:
            return
        by_kf: dict[int, list[tuple[MapLine, np.ndarray]]] = {}
        for j, L in lines.items():
            ml = self.lmap.lines.get(j)
            if ml is None or not np.all(np.isfinite(L)):
                continue
            ml.L = -L if L[3:] @ ml.L[3:] < 0 else L  # keep the orientation
            by_kf.setdefault(min(ml.observations), []).append((ml, ml.L))
        for k0, items in by_kf.items():  # end points re-clipped to the first view, batched per keyframe
            T = poses.get(k0, self.map.keyframes[k0].T_world_cam)
            segs = np.array([self.lmap.kf_feats[k0].segs[ml.observations[k0]] for ml, _ in items])
            a, b = pl.clip_to_segment(np.array([L for _, L in items]), segs, T, self.cam.K)
            for (ml, _), pa, pb in zip(items, a, b):
                if np.all(np.isfinite(pa)) and np.all(np.isfinite(pb)):
                    ml.ends = np.stack([pa, pb])
        if inliers is not None:
            for i in np.flatnonzero(~np.asarray(inliers, bool)):
                self.lmap.remove_observation(int(lp.obs_line[i]), int(lp.obs_kf[i]))

    def follow(self, delta: dict[int, np.ndarray]) -> None:
        """Every map line moves with its first keyframe, as the points do after a loop correction: x <- D x with
        D (4,4) = [s R | t] per keyframe (rigid, or a similarity for a monocular loop)."""
        for ml in self.lmap.lines.values():
            ref = ml.first_kf if ml.first_kf in delta else min((k for k in ml.observations if k in delta), default=None)
            if ref is not None:
                ml.L, ml.ends = moved_line(ml.L, ml.ends, delta[ref])

    def transform(self, T: np.ndarray, scale: float) -> None:
        """The whole line map into a new world, x_new = R (scale x_old) + t (``vio.transform_map``)."""
        D = np.array(T, dtype=np.float64)
        D[:3, :3] = D[:3, :3] * scale
        self.follow({k: D for k in self.map.keyframes})

    def cull(self, cur_kf: int) -> None:
        """Lines seen by too few keyframes ``cull_age`` keyframes after their creation are removed: a depth
        line by one, a two-view line by fewer than ``two_view_min_obs`` (its two creating views agree by
        construction, so only a third view confirms it)."""
        def too_few(ml: MapLine) -> bool:
            return len(ml.observations) < (self.cfg.two_view_min_obs if ml.two_view else 2)

        for j in [j for j, ml in self.lmap.lines.items() if cur_kf - ml.first_kf >= self.cfg.cull_age and too_few(ml)]:
            self.lmap.remove_line(j)

    def write_ply(self, path: Path) -> Path:
        """Map lines as a PLY line set (open3d imported here only)."""
        import open3d as o3d

        from vslam.outputs import atomic_path, write_text

        ends = np.array([ml.ends for ml in self.lmap.lines.values()], dtype=np.float64).reshape(-1, 3)
        if len(ends) == 0:  # open3d refuses an empty line set; the file still exists, with no elements
            write_text(path, "ply\nformat ascii 1.0\nelement vertex 0\nproperty double x\nproperty double y\n"
                                  "property double z\nelement edge 0\nproperty int vertex1\nproperty int vertex2\nend_header\n")
            return path
        ls = o3d.geometry.LineSet()
        ls.points = o3d.utility.Vector3dVector(ends)
        ls.lines = o3d.utility.Vector2iVector(np.arange(len(ends)).reshape(-1, 2))
        with atomic_path(path) as tmp:
            if not o3d.io.write_line_set(str(tmp), ls):
                raise OSError(errno.EIO, "could not write the line map (open3d)", str(path))
        return path

    def stats(self) -> dict[str, int]:
        return {"lines": len(self.lmap.lines), "line_observations": sum(len(m.observations) for m in self.lmap.lines.values())}
