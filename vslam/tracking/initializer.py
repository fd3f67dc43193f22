"""Monocular two-view map initialisation, after ORB-SLAM's ``Initializer``.

Mur-Artal, Montiel & Tardós, "ORB-SLAM: a Versatile and Accurate Monocular SLAM System",
IEEE T-RO 2015, §IV: fit a homography H (planar scene or pure rotation) and an epipolar model
(here the calibrated essential matrix E, 5-point; ORB-SLAM fits F with 8 points) to the same
matches, score both with the symmetric transfer error (eq. 1 of the paper; ``CheckHomography`` /
``CheckFundamental`` in the code), pick H when R_H = S_H / (S_H + S_F) > 0.45, then recover the
motion hypotheses of that model, triangulate, and accept only a clear winner with enough
parallax. Otherwise return None and let the tracker try again with a later frame: a refused
initialisation costs a few frames, a wrong one corrupts the whole map.

Both robust fits use OpenCV's USAC (MAGSAC++ scoring, local optimisation, final polishing) with
the RNG state taken from ``cfg.seed``, so results are deterministic without touching global RNG
state. pycolmap's LO-RANSAC E was slower with tuned trial counts and no more accurate here
(DEPENDENCIES.md §2), so OpenCV is used. ORB-SLAM runs the two fits in two threads; here they run one
after the other because a thread pool measured slower than sequential calls at these sizes (timings in
docs/tracking.md, "Monocular initialisation").

Frames: ``T_cur_ref`` maps reference-camera points into the current camera,
``p_cur = T_cur_ref @ p_ref``; the reference camera is the map's world frame at initialisation.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from vslam.geometry.se3 import inv_T, make_T
from vslam.geometry.triangulation import TwoViewTriangulation, as_pixels, triangulate_two_view

log = logging.getLogger(__name__)

# Chi-square 95 % quantiles (ORB-SLAM Initializer::CheckHomography / CheckFundamental):
_CHI2_1DOF = 3.841  # point-to-epipolar-line distance: inlier test for F/E
_CHI2_2DOF = 5.991  # transfer error: inlier test for H, and the score ceiling for both models
# ORB-SLAM's CheckRT: rays closer than this (cos > 0.99998, ~0.36 deg) may have any depth sign when
# counting support, and are never kept as map points.
_MIN_TRIANGULATION_DEG = np.degrees(np.arccos(0.99998))


@dataclass(frozen=True)
class InitConfig:
    min_matches: int = 100  # fewer matches between the two views -> do not try
    ransac_px: float = 1.0  # inlier threshold for E/H, pixels
    min_parallax_deg: float = 1.0  # median triangulation angle needed to accept the initialisation
    min_points: int = 50  # triangulated inliers needed
    h_ratio: float = 0.45  # ORB-SLAM's model selection: homography when S_H / (S_H + S_F) > h_ratio
    seed: int = 0
    sigma_px: float = 1.0  # keypoint noise used to normalise the S_H / S_F scores (ORB-SLAM: level-0 sigma)
    max_reproj_px: float = 2.0  # triangulated point kept if its reprojection error is below this (ORB-SLAM: 2 sigma)
    ambiguity_ratio: float = 0.7  # reject when the runner-up motion has > this fraction of the winner's support
    min_good_fraction: float = 0.9  # winner must triangulate this fraction of the model inliers (ORB-SLAM: 0.9)
    planar_inlier_ratio: float = 0.8  # also use H when H explains this fraction of E's inliers (COLMAP's max_H_inlier_ratio)
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    # Only well-conditioned points become map points: a model inlier triangulated under less parallax than this
    # still counts for the motion's support but is not kept (its depth is mostly noise). 0 = ORB-SLAM's 0.36 deg.
    point_min_parallax_deg: float = 0.0
    # Pair choice (``MonoInitializer``). 0 = the first frame that passes every test above makes the pair. > 0: a
    # passing frame is taken once its median parallax reaches this, or when waiting would lose the pair (matches
    # to the reference fell under ``keep_matches_ratio`` of those at the first passing frame, or the tries are
    # about to run out); a wider first baseline gives better-conditioned first depths.
    target_parallax_deg: float = 0.0
    keep_matches_ratio: float = 0.7
    # a pair whose accepted points are fewer than this fraction of its matches is refused (matches on movers,
    # repeated texture, a wrong model): 0 = no such test
    min_inlier_ratio: float = 0.0


@dataclass
class TwoViewResult:
    """T_cur_ref: (4,4) motion of the second view, scaled so the median depth of the points in the
    reference view is 1. pts_ref: (N,3) points in the reference camera frame (NaN where not
    triangulated); inliers: (N,) bool; model: "essential" or "homography"; parallax_deg: median.

    score_ratio: R_H = S_H / (S_H + S_F) that chose the model; support: (best, runner-up) number
    of matches each motion hypothesis explained (the ambiguity test compares them)."""

    T_cur_ref: np.ndarray
    pts_ref: np.ndarray
    inliers: np.ndarray
    model: str
    parallax_deg: float
    score_ratio: float = float("nan")
    support: tuple[int, int] = (0, 0)


def _usac(cfg: InitConfig) -> cv2.UsacParams:
    """USAC settings: MAGSAC++ with local optimisation, seeded from cfg (deterministic)."""
    p = cv2.UsacParams()
    p.sampler = cv2.SAMPLING_UNIFORM
    p.score = cv2.SCORE_METHOD_MAGSAC
    p.loMethod = cv2.LOCAL_OPTIM_SIGMA
    p.threshold = cfg.ransac_px
    p.confidence = cfg.ransac_confidence
    p.maxIterations = cfg.ransac_max_iters
    p.randomGeneratorState = cfg.seed
    p.isParallel = False
    return p


def _homog(uv: np.ndarray) -> np.ndarray:
    return np.hstack([uv, np.ones((len(uv), 1))])


def _transfer_sq(H: np.ndarray, x_from: np.ndarray, uv_to: np.ndarray) -> np.ndarray:
    """Squared pixel distance between uv_to and H x_from; inf where the transfer hits infinity."""
    y = x_from @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = np.sum((y[:, :2] / y[:, 2:3] - uv_to) ** 2, axis=1)
    return np.where(np.isfinite(d2), d2, np.inf)


def _line_dist_sq(F: np.ndarray, x_from: np.ndarray, x_to: np.ndarray) -> np.ndarray:
    """Squared pixel distance of x_to from the epipolar line F x_from."""
    lines = x_from @ F.T
    num = np.einsum("ij,ij->i", lines, x_to) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = num / (lines[:, 0] ** 2 + lines[:, 1] ** 2)
    return np.where(np.isfinite(d2), d2, np.inf)


def _score(chi_a: np.ndarray, chi_b: np.ndarray, th_in: float) -> tuple[float, np.ndarray]:
    """ORB-SLAM scoring: every direction under the inlier threshold adds (5.991 - chi2); a match
    is an inlier when both directions pass."""
    ok_a, ok_b = chi_a <= th_in, chi_b <= th_in
    s = np.sum(np.where(ok_a, _CHI2_2DOF - chi_a, 0.0)) + np.sum(np.where(ok_b, _CHI2_2DOF - chi_b, 0.0))
    return float(s), ok_a & ok_b


def score_homography(H: np.ndarray, uv_ref: np.ndarray, uv_cur: np.ndarray, sigma_px: float):
    """S_H and (N,) inlier mask for H mapping ref -> cur pixels (symmetric transfer error)."""
    x_ref, x_cur = _homog(uv_ref), _homog(uv_cur)
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return 0.0, np.zeros(len(uv_ref), bool)
    inv_s2 = 1.0 / sigma_px**2
    chi_cur = _transfer_sq(H, x_ref, uv_cur) * inv_s2
    chi_ref = _transfer_sq(H_inv, x_cur, uv_ref) * inv_s2
    return _score(chi_cur, chi_ref, _CHI2_2DOF)


def score_fundamental(F: np.ndarray, uv_ref: np.ndarray, uv_cur: np.ndarray, sigma_px: float):
    """S_F and (N,) inlier mask for F with x_cur^T F x_ref = 0 (symmetric epipolar distance)."""
    x_ref, x_cur = _homog(uv_ref), _homog(uv_cur)
    inv_s2 = 1.0 / sigma_px**2
    chi_cur = _line_dist_sq(F, x_ref, x_cur) * inv_s2
    chi_ref = _line_dist_sq(F.T, x_cur, x_ref) * inv_s2
    return _score(chi_cur, chi_ref, _CHI2_1DOF)


def _fit_models(uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray, cfg: InitConfig):
    """Robust H and E; each None when OpenCV finds no model. E may come back as a stack of 3x3."""
    params = _usac(cfg)
    try:
        H, _ = cv2.findHomography(uv_ref, uv_cur, params)
    except cv2.error:  # degenerate samples everywhere (e.g. all points collinear)
        H = None
    try:
        E, _ = cv2.findEssentialMat(uv_ref, uv_cur, K, K, None, None, params)
    except cv2.error:
        E = None
    H = H if H is not None and H.shape == (3, 3) and np.all(np.isfinite(H)) else None
    Es = [] if E is None or E.size < 9 else [e for e in np.asarray(E).reshape(-1, 3, 3) if np.all(np.isfinite(e))]
    return H, Es


def _motions_from_h(H: np.ndarray, K: np.ndarray) -> list[np.ndarray]:
    """Malis & Vargas (2007) decomposition: up to 4 (R, t/d) -> list of T_cur_ref (4,4)."""
    _, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
    return [make_T(R, t.ravel()) for R, t in zip(Rs, ts)]


def _motions_from_e(E: np.ndarray) -> list[np.ndarray]:
    """The four (R, +-t) of an essential matrix (H&Z §9.6.2) -> list of T_cur_ref (4,4), |t| = 1."""
    R1, R2, t = cv2.decomposeEssentialMat(E)
    t = t.ravel()
    return [make_T(R, s * t) for R in (R1, R2) for s in (1.0, -1.0)]


def _support(tri: TwoViewTriangulation, max_reproj_px: float) -> np.ndarray:
    """ORB-SLAM CheckRT: a match supports a motion when it reprojects well in both views and lies
    in front of both cameras, the depth sign being ignored for near-parallel rays."""
    low_par = tri.parallax_deg < _MIN_TRIANGULATION_DEG
    front = ((tri.depth1 > 0) & (tri.depth2 > 0)) | low_par
    return front & (tri.err1_px <= max_reproj_px) & (tri.err2_px <= max_reproj_px)


def _select_motion(motions, uv_ref, uv_cur, K, cfg: InitConfig):
    """Triangulate under every motion hypothesis T_cur_ref; return (T, triangulation, support of the
    best, support of the runner-up), or None when no hypothesis is usable."""
    best = None
    counts = []
    for T in motions:
        if not np.all(np.isfinite(T)) or np.linalg.norm(T[:3, 3]) < 1e-12:
            counts.append(0)
            continue
        tri = triangulate_two_view(np.eye(4), inv_T(T), uv_ref, uv_cur, K)
        n = int(np.count_nonzero(_support(tri, cfg.max_reproj_px)))
        counts.append(n)
        if best is None or n > best[2]:
            best = (T, tri, n)
    if best is None:
        return None
    second = sorted(counts)[-2] if len(counts) > 1 else 0
    return best[0], best[1], best[2], second


def initialize_two_view(uv_ref: np.ndarray, uv_cur: np.ndarray, K: np.ndarray, cfg: InitConfig = InitConfig()) -> TwoViewResult | None:
    """uv_ref, uv_cur: (N,2) matched ideal (undistorted) pixels; K (3,3). None when not well conditioned.

    Returns T_cur_ref (p_cur = T_cur_ref @ p_ref) with the translation scaled so that the median
    z of the accepted points in the reference camera is 1, the points in the reference frame with
    the same scale, and the mask of accepted matches (model inlier, in front of both cameras,
    parallax >= 0.36 deg, reprojection <= cfg.max_reproj_px in both views). None, with the reason
    logged at DEBUG, when: too few matches, no model, ambiguous motion, too few good points, or
    median parallax < cfg.min_parallax_deg (pure rotation, tiny baseline).
    """
    uv_ref, uv_cur = as_pixels(uv_ref, "uv_ref"), as_pixels(uv_cur, "uv_cur")
    K = np.asarray(K, dtype=np.float64)
    if uv_ref.shape != uv_cur.shape:
        raise ValueError(f"uv_ref and uv_cur differ in shape: {uv_ref.shape} vs {uv_cur.shape}")
    if not (np.all(np.isfinite(uv_ref)) and np.all(np.isfinite(uv_cur))):
        raise ValueError("uv_ref and uv_cur must be finite; drop unmatched rows before calling")
    n_all = len(uv_ref)
    if n_all < max(cfg.min_matches, 8):
        log.debug("init refused: %d matches < %d", n_all, cfg.min_matches)
        return None

    H, Es = _fit_models(uv_ref, uv_cur, K, cfg)
    s_h, in_h = score_homography(H, uv_ref, uv_cur, cfg.sigma_px) if H is not None else (0.0, None)
    K_inv = np.linalg.inv(K)
    s_f, in_f, E = 0.0, None, None
    for e in Es:  # several 5-point solutions can come back; keep the best scoring one
        s, inl = score_fundamental(K_inv.T @ e @ K_inv, uv_ref, uv_cur, cfg.sigma_px)
        if E is None or s > s_f:
            s_f, in_f, E = s, inl, e
    if s_h + s_f <= 0.0:
        log.debug("init refused: neither H nor E found")
        return None
    ratio = s_h / (s_h + s_f)
    # A plane fits two essential matrices equally well (H&Z §22.1.1 / Longuet-Higgins 1986), and the
    # cheirality test cannot tell them apart, so E on a (near-)planar scene is a coin toss. R_H alone
    # misses planes once the pixel noise approaches sigma_px (H's 2-dof error then scores worse than
    # E's 1-dof error), hence the extra inlier-ratio test used by COLMAP's two-view geometry.
    n_h = int(np.count_nonzero(in_h)) if in_h is not None else 0
    n_f = int(np.count_nonzero(in_f)) if in_f is not None else 0
    planar = n_h > 0 and n_h >= cfg.planar_inlier_ratio * n_f
    if ratio > cfg.h_ratio or planar:
        model, inl, motions = "homography", in_h, _motions_from_h(H, K)
    else:
        model, inl, motions = "essential", in_f, _motions_from_e(E)
    return _reconstruct(uv_ref, uv_cur, K, cfg, model, inl, motions, ratio)


def _reconstruct(uv_ref, uv_cur, K, cfg: InitConfig, model, inl, motions, ratio) -> TwoViewResult | None:
    """Pick the motion with clear support among the model's inliers, check it, fix the scale."""
    idx = np.flatnonzero(inl)
    n_in = len(idx)
    if n_in < cfg.min_points:
        log.debug("init refused (%s): %d model inliers < %d", model, n_in, cfg.min_points)
        return None
    sel = _select_motion(motions, uv_ref[idx], uv_cur[idx], K, cfg)
    if sel is None:
        log.debug("init refused (%s): no valid motion hypothesis", model)
        return None
    T, tri, n_best, n_second = sel
    if n_best < max(cfg.min_points, cfg.min_good_fraction * n_in):
        log.debug("init refused (%s): best motion explains %d of %d inliers", model, n_best, n_in)
        return None
    if n_second > cfg.ambiguity_ratio * n_best:
        log.debug("init refused (%s): ambiguous motion, support %d vs %d", model, n_best, n_second)
        return None
    good = tri.ok(_MIN_TRIANGULATION_DEG, cfg.max_reproj_px)
    n_good = int(np.count_nonzero(good))
    parallax = float(np.median(tri.parallax_deg[good])) if n_good else 0.0
    if n_good < cfg.min_points or parallax < cfg.min_parallax_deg:
        log.debug("init refused (%s): %d good points, median parallax %.2f deg", model, n_good, parallax)
        return None
    if cfg.point_min_parallax_deg > _MIN_TRIANGULATION_DEG:  # keep the well-conditioned points only
        good &= tri.parallax_deg >= cfg.point_min_parallax_deg
        if int(np.count_nonzero(good)) < cfg.min_points:
            log.debug("init refused (%s): %d points above %.2f deg parallax", model, int(np.count_nonzero(good)),
                      cfg.point_min_parallax_deg)
            return None

    scale = 1.0 / float(np.median(tri.depth1[good]))
    T_cur_ref = T.copy()
    T_cur_ref[:3, 3] *= scale
    pts_ref = np.full((len(uv_ref), 3), np.nan)
    inliers = np.zeros(len(uv_ref), dtype=bool)
    pts_ref[idx[good]] = tri.pts_world[good] * scale
    inliers[idx[good]] = True
    return TwoViewResult(T_cur_ref, pts_ref, inliers, model, parallax, float(ratio), (n_best, n_second))
