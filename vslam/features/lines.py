"""2-D line segments: LSD detection, a band (LBD-style) descriptor, and matching with geometric checks.

Detector: OpenCV's LSD (``cv2.createLineSegmentDetector``, in the plain headless wheel; FLD/EDLines need
opencv-contrib, see DEPENDENCIES.md §5), segments shorter than ``min_length_px`` dropped, the longest
``max_lines`` kept, near-duplicates (same line, overlapping) suppressed.

Descriptor (after LBD, Zhang & Koch 2013, without its Gaussian weights): the image gradient is sampled on a
grid of ``n_along`` points along the segment times ``n_bands`` x ``band_px`` pixels across it; per band the
mean and std of the four clipped projections (g.n)+, (g.n)-, (g.d)+, (g.d)- form 8 numbers; the vector is
L2-normalised (float32, L2 distance). Segments are oriented so that the mean gradient points to their
right-hand normal, which makes the descriptor and the matching angle test direction-consistent.

All pixel arrays are ``(N, 4)`` rows (u1, v1, u2, v2); ``raw`` in the distorted image, ``segs`` ideal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from vslam.data.types import PinholeCamera


@dataclass(frozen=True)
class LineConfig:
    """Line features. ``enabled``: False keeps the point-only system unchanged (the default)."""

    enabled: bool = False
    min_length_px: float = 30.0  # shorter segments carry little direction and are unstable across frames
    max_lines: int = 120  # longest first
    n_along: int = 9  # descriptor samples along the segment
    n_bands: int = 5  # descriptor bands across it ...
    band_px: float = 2.0  # ... each this wide
    # L2 distance of unit descriptors: above most correct pairs, the geometric gates do the rest
    # (distributions on the synthetic room: docs/lines.md, 'Measurements behind settings in the code')
    max_desc_dist: float = 0.3
    match_angle_deg: float = 8.0  # oriented angle difference allowed in matching
    match_radius_px: float = 12.0  # end points of a candidate within this distance of the predicted line
    min_overlap: float = 0.3  # overlap along the line / shorter segment
    # std of an end-point distance, pixels (pose-only tracking and local BA). 1 px rather than 2, chosen on
    # validation runs the bench rows do not use (corridors, TUM teddy and KITTI 07 at other ORB budgets); what
    # 1 px buys is the pose-only weight (docs/lines.md).
    pixel_sigma: float = 1.0
    min_depth_samples: int = 5  # RGB-D/stereo line creation: valid depth samples needed along the segment
    depth_fit_m: float = 0.03  # ... max deviation of those samples from the 3-D line (+ 1 % of depth)
    max_new_lines: int = 60  # line landmarks created per keyframe
    # create lines only where the depth on both sides of the segment agrees: an occluding contour of a curved
    # object (TUM teddy's bear) is no fixed 3-D line, and Kinect depth bleeds there. Off: it also rejects the
    # crease lines (wall/floor) that carry the corridor (docs/lines.md, 'Measurements behind settings in the code').
    surface_only: bool = False
    # the same without losing creases: each side's depth (2 and 4 px off the segment) extrapolated linearly to
    # the segment; a crease's two surfaces meet there, an occluding contour's do not (sides without depth: not
    # judged). Chosen on TUM teddy with lines at several ORB budgets, the corridor unchanged (docs/lines.md).
    reject_contours: bool = True
    # most-observed map lines put into one local BA; the line share of BA time scales with it. Chosen on the
    # synthetic corridor, accuracy against BA time (docs/lines.md, 'Measurements behind settings in the code')
    ba_max_lines: int = 60
    # A line joins local BA once this many of the window's keyframes see it; 0 = 3 for monocular, 2 otherwise.
    # A monocular two-view line is weak until a third view confirms it; not for the others, where 2 views
    # gave the better ATE (docs/lines.md, 'Measurements behind settings in the code').
    ba_min_views: int = 0
    weight: float = 1.0  # pose-only: line residual weight relative to points
    # RGB-D: each observed end point also measures its depth (the segment's depth samples, each side
    # extrapolated to it, fitted by a 3-D line), entering pose-only tracking and local BA as a virtual disparity
    # fx b / z (b the RGB-D virtual baseline, as for the points) of this std in pixels: two more rows per
    # observation, so a line seen by two keyframes already constrains them; 0 = lines are image-only. Chosen
    # on validation corridors the bench rows do not use (docs/lines.md). Synthetic depth is exact; Kinect depth
    # bleeds at edges, and the TUM presets use 0.3 (see there).
    depth_sigma_px: float = 0.05
    # Stereo: the same end-point depth rows, measured by intersecting the planes of the segment and its match
    # in the right image (descriptor + epipolar overlap, as two-view creation, crossing the epipolar lines at
    # >= ``stereo_min_epi_angle_deg``: along them the planes coincide); std of that disparity in pixels, 0 =
    # off. Chosen on validation stereo corridors the bench rows do not use (docs/lines.md). Costs a second LSD
    # pass (the right image) on the front-end thread.
    stereo_depth_sigma_px: float = 0.2
    stereo_min_epi_angle_deg: float = 20.0
    # RGB-D line creation reads each side's depth extrapolated to the segment, as the depth rows do, instead of
    # the nearer side 2 px off (centimetres nearer than the segment on a wall seen at a slant): docs/lines.md,
    # 'Measurements behind settings in the code'
    create_extrapolate: bool = True
    # where new line landmarks come from: "depth" (RGB-D: the depth map along the segment; stereo: the end-point
    # depths the rig measured, ``stereo_depth_sigma_px``), "two_view" (a new keyframe's segments matched to a
    # covisible keyframe's by epipolar overlap, planes intersected), "both" (depth first, two-view for what it
    # left); "auto": depth for RGB-D, both for stereo, two-view for mono. For stereo "both": the rig misses
    # lines along its epipolar lines and far ones, two views over the motion take those (docs/lines.md).
    create: Literal["auto", "depth", "two_view", "both"] = "auto"
    rig_min_disparity_px: float = 2.0  # stereo "depth" creation: both end points at least this disparity
    tri_min_epi_angle_deg: float = 5.0  # two-view: a segment must cross the epipolar lines at least this steeply
    tri_min_angle_deg: float = 2.0  # ... and the two back-projected planes meet at least at this angle
    # ... and each end point is seen from the two centres at this angle. Chosen on the stereo corridor's
    # validation seeds; at smaller angles far end points tilted corridor-long lines (docs/lines.md, 'Measurements
    # behind settings in the code')
    tri_min_parallax_deg: float = 3.0
    two_view_min_obs: int = 3  # a two-view line still seen by fewer keyframes ``cull_age`` keyframes later goes
    cull_age: int = 3


@dataclass
class LineFeatures:
    """Segments of one image: raw/segs (N,4) px; desc (N,D) float32; length (N,) px (ideal); rho (N,2) the
    end points' measured inverse depths, 1/m (RGB-D / stereo, ``LineSlam.detect``; NaN: none), or None."""

    raw: np.ndarray
    segs: np.ndarray
    desc: np.ndarray
    length: np.ndarray
    rho: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.segs)

    def subset(self, idx: np.ndarray) -> LineFeatures:
        rho = None if self.rho is None else self.rho[idx]
        return LineFeatures(self.raw[idx], self.segs[idx], self.desc[idx], self.length[idx], rho)

    @staticmethod
    def empty(dim: int) -> LineFeatures:
        return LineFeatures(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, dim), np.float32), np.zeros(0))


class LineExtractor:
    """LSD + band descriptor; ``detect(image, camera) -> LineFeatures``."""

    def __init__(self, cfg: LineConfig = LineConfig()):
        self.cfg = cfg
        self.lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        self.dim = 8 * cfg.n_bands

    def detect(self, image: np.ndarray, camera: PinholeCamera) -> LineFeatures:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        out = self.lsd.detect(gray)[0]
        if out is None or len(out) == 0:
            return LineFeatures.empty(self.dim)
        raw = np.asarray(out, dtype=np.float64).reshape(-1, 4)
        length = np.hypot(raw[:, 2] - raw[:, 0], raw[:, 3] - raw[:, 1])
        raw = raw[length >= self.cfg.min_length_px]
        raw = raw[np.argsort(-np.hypot(raw[:, 2] - raw[:, 0], raw[:, 3] - raw[:, 1]), kind="stable")]
        raw = suppress_duplicates(raw[: 3 * self.cfg.max_lines])[: self.cfg.max_lines]
        if len(raw) == 0:
            return LineFeatures.empty(self.dim)
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        raw = orient(raw, gx, gy)
        desc = band_descriptor(raw, gx, gy, self.cfg)
        segs = camera.undistort_points(raw.reshape(-1, 2)).reshape(-1, 4) if camera.is_distorted else raw.copy()
        return LineFeatures(raw, segs, desc, np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]))


def suppress_duplicates(raw: np.ndarray, angle_deg: float = 3.0, dist_px: float = 2.0) -> np.ndarray:
    """Drop a segment (rows sorted longest first) lying within ``dist_px`` of a longer kept one's line, at
    the same direction, and overlapping it by half its own length: LSD splits one edge into twins on a
    blurred step. Pairwise tests are vectorised; only the greedy pass over the flagged pairs loops."""
    n = len(raw)
    if n < 2:
        return raw
    d = raw[:, 2:] - raw[:, :2]
    ln = np.hypot(d[:, 0], d[:, 1])
    u = d / ln[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    par = np.abs(u @ u.T) >= np.cos(np.radians(angle_deg))  # [i, j]
    r1 = raw[:, None, :2] - raw[None, :, :2]  # i's end points relative to j's start
    r2 = raw[:, None, 2:] - raw[None, :, :2]
    near = np.maximum(np.abs(np.einsum("ijk,jk->ij", r1, nrm)), np.abs(np.einsum("ijk,jk->ij", r2, nrm))) <= dist_px
    s1, s2 = np.einsum("ijk,jk->ij", r1, u), np.einsum("ijk,jk->ij", r2, u)
    ov = np.minimum(np.maximum(s1, s2), ln[None, :]) - np.maximum(np.minimum(s1, s2), 0.0)
    dup = par & near & (ov > 0.5 * ln[:, None]) & (np.arange(n)[None, :] < np.arange(n)[:, None])  # j longer
    keep = np.ones(n, bool)
    for i in np.flatnonzero(dup.any(axis=1)):
        if (dup[i] & keep).any():
            keep[i] = False
    return raw[keep]


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return cv2.remap(img, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def orient(raw: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Swap end points so the mean gradient across each segment points along its right-hand normal."""
    d = raw[:, 2:] - raw[:, :2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    t = np.linspace(0.1, 0.9, 7)
    pts = raw[:, None, :2] + t[None, :, None] * (raw[:, None, 2:] - raw[:, None, :2])
    g = np.stack([_sample(gx, pts[..., 0], pts[..., 1]), _sample(gy, pts[..., 0], pts[..., 1])], axis=-1)
    flip = np.einsum("nk,nk->n", g.mean(axis=1), nrm) < 0
    out = raw.copy()
    out[flip] = raw[flip][:, [2, 3, 0, 1]]
    return out


def band_descriptor(raw: np.ndarray, gx: np.ndarray, gy: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """(N,4) oriented segments -> (N, 8 n_bands) float32 unit descriptors (see the module docstring)."""
    n = len(raw)
    d = raw[:, 2:] - raw[:, :2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.stack([-d[:, 1], d[:, 0]], axis=1)
    t = np.linspace(0.05, 0.95, cfg.n_along)
    half = cfg.n_bands * cfg.band_px / 2.0
    across = np.arange(-half + 0.5, half, 1.0)  # one sample per pixel row across the bands
    base = raw[:, None, :2] + t[None, :, None] * (raw[:, None, 2:] - raw[:, None, :2])  # (N,A,2)
    pts = base[:, :, None, :] + across[None, None, :, None] * nrm[:, None, None, :]  # (N,A,C,2)
    x, y = pts[..., 0].reshape(n, -1), pts[..., 1].reshape(n, -1)
    sx, sy = _sample(gx, x, y).reshape(pts.shape[:3]), _sample(gy, x, y).reshape(pts.shape[:3])
    gn = sx * nrm[:, None, None, 0] + sy * nrm[:, None, None, 1]
    gd = sx * d[:, None, None, 0] + sy * d[:, None, None, 1]
    parts = np.stack([np.maximum(gn, 0), np.maximum(-gn, 0), np.maximum(gd, 0), np.maximum(-gd, 0)], axis=-1)  # (N,A,C,4)
    band = np.minimum(((across + half) / cfg.band_px).astype(np.int64), cfg.n_bands - 1)
    desc = []
    for b in range(cfg.n_bands):
        p = parts[:, :, band == b, :].reshape(n, -1, 4)
        desc += [p.mean(axis=1), p.std(axis=1)]
    out = np.concatenate(desc, axis=1).astype(np.float32)
    out /= np.linalg.norm(out, axis=1, keepdims=True) + 1e-12
    return out


def match_lines(pred: np.ndarray, pred_desc: np.ndarray, frame: LineFeatures, cfg: LineConfig,
                radius_px: float | None = None) -> np.ndarray:
    """Guided matching of predicted segments (map lines projected with a pose guess) to a frame's segments.

    pred: (P,4) predicted oriented segments, ideal pixels; pred_desc: (P,D). A candidate must have the same
    direction within ``match_angle_deg``, both end points within ``radius_px`` of the predicted infinite line,
    overlap >= ``min_overlap`` of the shorter segment along it, and descriptor distance <= ``max_desc_dist``;
    the nearest descriptor wins, each frame segment used once (smallest distance keeps it).
    -> (M,2) int pairs (pred index, frame index), sorted by pred index.
    """
    empty = np.zeros((0, 2), np.int64)
    if len(pred) == 0 or len(frame) == 0:
        return empty
    r = cfg.match_radius_px if radius_px is None else radius_px
    dp = pred[:, 2:] - pred[:, :2]
    lp = np.linalg.norm(dp, axis=1)
    up = dp / np.maximum(lp, 1e-9)[:, None]
    nrm = np.stack([-up[:, 1], up[:, 0]], axis=1)
    f = frame.segs
    df = f[:, 2:] - f[:, :2]
    uf = df / np.maximum(np.linalg.norm(df, axis=1), 1e-9)[:, None]
    cos_ok = up @ uf.T >= np.cos(np.radians(cfg.match_angle_deg))  # (P,F), oriented
    rel1 = f[None, :, :2] - pred[:, None, :2]  # (P,F,2)
    rel2 = f[None, :, 2:] - pred[:, None, :2]
    d1 = np.abs(np.einsum("pfk,pk->pf", rel1, nrm))
    d2 = np.abs(np.einsum("pfk,pk->pf", rel2, nrm))
    s1, s2 = np.einsum("pfk,pk->pf", rel1, up), np.einsum("pfk,pk->pf", rel2, up)
    overlap = np.minimum(np.maximum(s1, s2), lp[:, None]) - np.maximum(np.minimum(s1, s2), 0.0)
    shorter = np.minimum(lp[:, None], np.abs(s2 - s1))
    ok = cos_ok & (d1 <= r) & (d2 <= r) & (overlap >= cfg.min_overlap * np.maximum(shorter, 1e-9))
    return _best_unique(np.where(ok, _desc_dist(pred_desc, frame.desc), np.inf), cfg.max_desc_dist)


def match_epipolar_segments(segs_a: np.ndarray, desc_a: np.ndarray, segs_b: np.ndarray, desc_b: np.ndarray,
                            F_b_a: np.ndarray, cfg: LineConfig) -> np.ndarray:
    """Matches between two keyframes' segments for two-view line triangulation (no map line to predict from).

    segs_*: (A,4) / (B,4) oriented segments, ideal pixels; desc_*: their descriptors; F_b_a: (3,3) fundamental
    matrix, x_b^T F x_a = 0. A pair must (1) be a descriptor match (<= ``max_desc_dist``), (2) cut the
    epipolar lines of a's end points at a usable angle (>= ``tri_min_epi_angle_deg``: a segment along the
    epipolar lines has no second-view constraint and its triangulation is degenerate), (3) keep its
    orientation -- a's end points, carried to b's line along their epipolar lines, come out in b's order --
    and (4) overlap b by ``min_overlap`` of the shorter of b and that carried span, whose length is within
    4x of b's (LSD cuts an edge differently in two views; much more is another edge). Schmid & Zisserman
    1997 match lines by this epipolar overlap. -> (M,2) pairs (index in a, index in b), each b used once.
    """
    empty = np.zeros((0, 2), np.int64)
    if len(segs_a) == 0 or len(segs_b) == 0:
        return empty
    one_a = np.ones((len(segs_a), 1))
    e1 = np.hstack([segs_a[:, :2], one_a]) @ F_b_a.T  # (A,3) epipolar lines in b of a's end points
    e2 = np.hstack([segs_a[:, 2:], one_a]) @ F_b_a.T
    b1, db = segs_b[:, :2], segs_b[:, 2:] - segs_b[:, :2]
    lb = np.maximum(np.linalg.norm(db, axis=1), 1e-9)
    ub = db / lb[:, None]
    # where b1 + s ub meets the line e: e . (b1, 1) + s e[:2] . ub = 0
    s_pts, sin_ok = [], np.ones((len(segs_a), len(segs_b)), bool)
    for e in (e1, e2):
        num = -(e[:, :2] @ b1.T + e[:, 2:3])  # (A,B)
        den = e[:, :2] @ ub.T
        en = np.maximum(np.linalg.norm(e[:, :2], axis=1), 1e-12)
        ok = np.abs(den) >= np.sin(np.radians(cfg.tri_min_epi_angle_deg)) * en[:, None]
        sin_ok &= ok
        with np.errstate(divide="ignore", invalid="ignore"):
            s_pts.append(np.where(ok, num / np.where(ok, den, 1.0), np.nan))
    s1, s2 = s_pts
    span = s2 - s1
    overlap = np.minimum(s2, lb[None, :]) - np.maximum(s1, 0.0)
    shorter = np.minimum(span, lb[None, :])
    ok = sin_ok & (span > 0.25 * lb[None, :]) & (span < 4.0 * lb[None, :]) & (overlap >= cfg.min_overlap * shorter)
    return _best_unique(np.where(ok, _desc_dist(desc_a, desc_b), np.inf), cfg.max_desc_dist)


def _desc_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A,D), (B,D) unit descriptors -> (A,B) L2 distances."""
    return np.sqrt(np.maximum(2.0 - 2.0 * (a @ b.T), 0.0))


def _best_unique(dist: np.ndarray, max_dist: float) -> np.ndarray:
    """Row-wise nearest column within ``max_dist`` (inf = not allowed); a column claimed by several rows
    goes to the smallest distance. -> (M,2) (row, column), sorted by row."""
    dist = np.where(dist > max_dist, np.inf, dist)
    best = np.argmin(dist, axis=1)
    bd = dist[np.arange(len(dist)), best]
    pi = np.flatnonzero(np.isfinite(bd))
    if len(pi) == 0:
        return np.zeros((0, 2), np.int64)
    fi, bd = best[pi], bd[pi]
    order = np.lexsort((pi, bd, fi))
    pi, fi = pi[order], fi[order]
    keep = np.r_[True, fi[1:] != fi[:-1]]
    out = np.stack([pi[keep], fi[keep]], axis=1)
    return out[np.argsort(out[:, 0], kind="stable")]
