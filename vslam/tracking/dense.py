"""Dense geometric tracking for RGB-D frames where features are too few (white walls, a floor).

When feature tracking fails, the frame's depth is registered against the reference keyframe's: multi-scale
point-to-plane ICP (Chen & Medioni 1992) over a voxel pyramid, started from the motion model's prediction.
The pose covariance and a degeneracy test come from the final correspondences. Geometry cannot measure a
motion parallel to every visible surface (across a single wall, along a corridor whose end is out of depth
range): such frames are refused, not guessed.

Open3D voxel-downsamples the clouds; the Gauss-Newton steps are here, in numpy with scipy's KD-tree, because
Open3D's ``registration_icp`` is not repeatable (threaded reductions: 8 calls on the same input gave 8
results, 1e-14 apart) and the tracker promises the same poses for the same input; and because its
``get_information_matrix_from_point_clouds`` is the point-to-point information, full rank even for one plane.
Coloured ICP (Park et al. 2017) is not used: on the corridor its image term did not hold the axis the
geometry leaves free, and Open3D's recomputes the reference's colour gradients on every call (its cost:
docs/tracking.md, "Dense tracking").

Clouds come from a subsampled depth image (about ``cloud_width`` columns); normals from the depth grid. The
reference keyframe's pyramid is built on its first use only: most keyframes are never needed here.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from vslam.data.types import PinholeCamera
from vslam.geometry.se3 import adjoint, inv_T, make_T, so3_exp

log = logging.getLogger(__name__)

# A depth-grid normal is kept when its four neighbours lie within this fraction of the depth from its plane
# (1 cm at 1 m): not across an edge or a depth jump.
_PLANAR_TOL = 0.01
_NORMAL_AGREE = 0.985  # |mean of a voxel's unit normals|: two equal halves 20 degrees apart give this
_STEP_TOL = 1e-6  # a level stops when a Gauss-Newton step is below this (rad, m)


@dataclass(frozen=True)
class DenseConfig:
    # On by default: it runs only on RGB-D frames that feature tracking failed, so runs where features track
    # are unchanged, and a frame it cannot measure stays "predicted" as before.
    enabled: bool = True
    cloud_width: int = 80  # the depth image is subsampled to about this many columns (every 4th px at 320x240)
    min_depth: float = 0.2  # metres; depth outside [min, max] is not used
    max_depth: float = 8.0  # beyond, consumer depth sensors are too noisy and sparse
    min_points: int = 500  # valid subsampled depth pixels needed in the frame (and the reference)
    # metres, coarse to fine; the finest ~ the sample spacing at 3 m. A finer pyramid with more steps gained
    # little accuracy for much more time (docs/tracking.md, "Dense tracking")
    voxel_sizes: tuple[float, ...] = (0.2, 0.1, 0.05)
    # correspondence gates, one per level: the coarsest covers the motion model's error after a second or
    # so without features (10-20 cm), the finest sub-voxel misalignment
    max_correspondence: tuple[float, ...] = (0.3, 0.15, 0.075)
    iterations: tuple[int, ...] = (6, 5, 4)  # Gauss-Newton steps per level (fewer when a step is < 1e-6)
    # share of the frame's points with a reference point within the finest gate (and 3 robust sigmas). A lower
    # share accepted wrong TUM teddy pairs (docs/tracking.md, "Dense tracking")
    min_fitness: float = 0.6
    # below this share the frame becomes the reference (and a keyframe where its keypoints have depth): on a
    # long stretch without features the reference would otherwise fall behind until min_fitness refuses
    keyframe_fitness: float = 0.7
    max_rmse: float = 0.015  # metres, point-to-plane RMS of those correspondences (a Kinect's noise at ~2 m)
    # Degeneracy (Gelfand et al. 2003, "Geometrically stable sampling for the ICP algorithm"): the smallest
    # eigenvalue of the point-to-plane information per correspondence, rotations scaled by the mean point
    # distance; 0 for one plane or a corridor seen along its axis. The threshold separates the synthetic pairs
    # ICP measured well from those it did not (docs/tracking.md, "Dense tracking").
    min_constraint: float = 0.001
    # per-point depth noise for the covariance (the measured residual RMS when larger). Neighbouring points'
    # errors are correlated, so the covariance is a lower bound, like the feature tracker's.
    depth_sigma: float = 0.005
    # The relative pose of a keyframe made from a dense frame enters BA (``Map.links``) with the ICP covariance
    # plus these variances: the covariance above assumes independent points, and on real pairs it is far too
    # small (docs/tracking.md, "Dense tracking"; depth-to-colour timing and rolling shutter are not in it).
    link_sigma_deg: float = 1.0
    link_sigma_m: float = 0.02


@dataclass
class DenseResult:
    """T_world_cam (4,4) and T_ref_cam (4,4, reference keyframe <- frame); cov (6,6): (rotation rad,
    translation m) of the left perturbation of T_cam_world, as ``FrameEstimate.pose_cov`` (the reference
    keyframe's pose taken as exact); fitness (share of the frame's points matched), rmse (metres,
    point-to-plane), constraint (the degeneracy measure, see ``DenseConfig.min_constraint``), n_corr
    (inlier correspondences), ms (time of the step)."""

    T_world_cam: np.ndarray
    T_ref_cam: np.ndarray
    cov: np.ndarray
    fitness: float
    rmse: float
    constraint: float
    n_corr: int
    ms: float


@dataclass
class _Level:
    """One pyramid level of the reference: points (N,3) and unit normals (N,3), its camera frame; KD-tree."""

    pts: np.ndarray
    nrm: np.ndarray
    tree: object


class DenseOdometry:
    """ICP of a frame's depth against one reference keyframe's; ``set_reference`` then ``track`` per frame."""

    def __init__(self, cam: PinholeCamera, cfg: DenseConfig = DenseConfig()):
        n = len(cfg.voxel_sizes)
        if not (n and len(cfg.max_correspondence) == n and len(cfg.iterations) == n):
            raise ValueError("dense: voxel_sizes, max_correspondence and iterations need one entry per level")
        self.cam, self.cfg = cam, cfg
        self.step = max(1, int(round(cam.width / cfg.cloud_width)))
        self.ref_id: int | None = None
        self.T_world_ref = np.eye(4)
        # (reference keyframe id, T_ref_cam, covariance with the link floors) of the last frame measured
        # against a map keyframe: the tracker makes it a ``PoseLink`` when that frame becomes a keyframe
        self.last_link: tuple[int, np.ndarray, np.ndarray] | None = None
        # (keyframe id, T_kf_ref, its covariance): where the reference is a frame outside the map, its relative
        # pose to the last keyframe reference, compounded over the frames between, so a link still ends there
        self._chain: tuple[int, np.ndarray, np.ndarray] | None = None
        self._ref_raw: tuple[np.ndarray, np.ndarray] | None = None  # points (N,3) in the reference camera, normals
        self._ref_levels: list[_Level] | None = None
        self._rays: np.ndarray | None = None
        self.last_reason = ""  # why the last ``track`` returned None (for logs and tests)
        self.wants_keyframe = False  # the frame just tracked by ``track_frame`` should become a keyframe

    # -- clouds -----------------------------------------------------------------
    def _cloud(self, depth: np.ndarray | None, normals: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Subsampled back-projection: (N,3) camera-frame points, metres, and with ``normals`` (N,3) unit
        normals facing the camera (points without one are dropped), else None.

        Normals come from the depth grid (cross product of the neighbours' differences), not from k nearest
        points: along a wall seen at a grazing angle the far samples are sparse, and neighbour fits there
        mixed surfaces into normals with a component along a corridor's axis, a constraint that is not there."""
        if depth is None:
            return np.zeros((0, 3)), np.zeros((0, 3)) if normals else None
        s = self.step
        d = np.asarray(depth[::s, ::s], dtype=np.float64)
        if self._rays is None or self._rays.shape[:2] != d.shape:
            v, u = np.mgrid[0 : depth.shape[0] : s, 0 : depth.shape[1] : s]
            uv = self.cam.undistort_points(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
            self._rays = self.cam.backproject(uv, np.ones(len(uv))).reshape(*d.shape, 3)
        ok = np.isfinite(d) & (d > self.cfg.min_depth) & (d < self.cfg.max_depth)
        P = self._rays * np.where(ok, d, np.nan)[..., None]
        if not normals:
            return P[ok], None
        c = P[1:-1, 1:-1]
        nbs = (P[1:-1, 2:], P[1:-1, :-2], P[2:, 1:-1], P[:-2, 1:-1])
        with np.errstate(invalid="ignore"):
            n = np.cross(nbs[0] - nbs[1], nbs[2] - nbs[3])
            n /= np.linalg.norm(n, axis=-1, keepdims=True)
            n *= -np.sign(np.einsum("hwi,hwi->hw", n, c))[..., None]  # towards the camera
            dev = np.max([np.abs(np.einsum("hwi,hwi->hw", n, nb - c)) for nb in nbs], axis=0)
            n[~(dev < _PLANAR_TOL * c[..., 2])] = np.nan
        nrm = np.full_like(P, np.nan)
        nrm[1:-1, 1:-1] = n
        ok &= np.isfinite(nrm[..., 0])
        return P[ok], nrm[ok]

    def set_reference(self, kf_id: int | None, T_world_cam: np.ndarray, depth: np.ndarray | None,
                      image: np.ndarray | None = None) -> None:
        """The keyframe later frames are registered against (None: a frame outside the map); depth (H,W)
        float metres, 0 = invalid; ``image`` is not used (kept for a photometric term). Its subsampled cloud
        is kept; the pyramid is built on first use."""
        self.ref_id, self.T_world_ref = kf_id, np.asarray(T_world_cam, dtype=np.float64).copy()
        self._chain = None if kf_id is None else (kf_id, np.eye(4), np.zeros((6, 6)))
        self._ref_raw = self._cloud(depth, normals=True)  # type: ignore[assignment]
        self._ref_levels = None
        self.wants_keyframe = False

    def clear_reference(self) -> None:
        """No reference until the next ``set_reference``: frames are refused."""
        self.ref_id, self._chain, self._ref_raw, self._ref_levels = None, None, None, None
        self.wants_keyframe = False

    def _levels(self) -> list[_Level]:
        import open3d as o3d
        from scipy.spatial import cKDTree

        if self._ref_levels is None:
            pts, nrm = self._ref_raw  # type: ignore[misc]
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pcd.normals = o3d.utility.Vector3dVector(nrm)
            levels = []
            for v in self.cfg.voxel_sizes:
                down = pcd.voxel_down_sample(v)  # points and normals averaged per voxel
                p, n = np.asarray(down.points), np.asarray(down.normals)
                # A voxel across two surfaces (where a wall meets the ceiling) gets a point between them and a
                # normal of neither; its mean normal is short: keep the voxels whose normals agree.
                length = np.linalg.norm(n, axis=1)
                keep = length > _NORMAL_AGREE
                levels.append(_Level(p[keep], n[keep] / length[keep, None], cKDTree(p[keep])))
            self._ref_levels = levels
        return self._ref_levels

    # -- tracking ---------------------------------------------------------------
    def track(self, depth: np.ndarray | None, image: np.ndarray | None, T_pred: np.ndarray,
              T_world_ref: np.ndarray | None = None) -> DenseResult | None:
        """Pose of the frame (depth (H,W) float metres, 0 = invalid; ``image`` not used) from the prediction
        T_pred (4,4 T_world_cam); ``T_world_ref``: the reference keyframe's current pose (local BA moves it;
        None = as given to ``set_reference``). None when the result is not trustworthy (``last_reason``)."""
        import open3d as o3d

        t0 = time.perf_counter()
        cfg = self.cfg
        if self._ref_raw is None or len(self._ref_raw[0]) < cfg.min_points:
            return self._refuse("reference keyframe has too few depth points")
        pts, _ = self._cloud(depth)
        if len(pts) < cfg.min_points:
            return self._refuse(f"{len(pts)} depth points")
        T_w_ref = self.T_world_ref if T_world_ref is None else np.asarray(T_world_ref, dtype=np.float64)
        # T_ref_cam. Re-orthonormalised: the motion model (velocity = inv_T(T_prev) @ T) doubles a start's
        # departure from a rotation with every frame tracked here, and updates composed onto it keep it
        T = _rigid(inv_T(T_w_ref) @ np.asarray(T_pred, dtype=np.float64))
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        levels = self._levels()
        for i, (lvl, v, dmax, iters) in enumerate(zip(levels, cfg.voxel_sizes, cfg.max_correspondence, cfg.iterations)):
            q = np.asarray(src.voxel_down_sample(v).points)
            for it in range(iters):
                lin = _linearize(q, T, lvl, dmax)
                if lin is None:
                    return self._refuse("no correspondences")
                J, r, used = lin
                if i == it == 0 and _constraint(J, q[used]) < cfg.min_constraint:
                    # at the prediction already: the steps would slide along the free direction
                    return self._refuse(f"degenerate: constraint {_constraint(J, q[used]):.4f}")
                # Tukey weights at the voxel size: where two surfaces meet, residuals of cm
                w = np.where(np.abs(r) < v, (1.0 - (r / v) ** 2) ** 2, 0.0)
                H = (J * w[:, None]).T @ J
                xi = -np.linalg.lstsq(H, J.T @ (w * r), rcond=1e-6)[0]  # a free direction stays where it is
                T = _rigid(T @ make_T(so3_exp(xi[:3]), xi[3:]))
                if np.linalg.norm(xi) < _STEP_TOL:
                    break
        return self._assess(q, T, T_w_ref, levels[-1], cfg.max_correspondence[-1], t0)

    def _assess(self, q: np.ndarray, T: np.ndarray, T_w_ref: np.ndarray, lvl: _Level, dmax: float,
                t0: float) -> DenseResult | None:
        """The checks and the covariance at the final pose T (T_ref_cam) of the finest level's points q."""
        cfg = self.cfg
        lin = _linearize(q, T, lvl, dmax)
        if lin is None:
            return self._refuse("no correspondences")
        J, r, used = lin
        # inliers within 3 robust sigmas (MAD) for the statistics
        scale = max(1.4826 * float(np.median(np.abs(r))), cfg.depth_sigma / 3)
        inl = np.abs(r) <= 3.0 * scale
        J, r, used = J[inl], r[inl], used[inl]
        fitness, rmse = len(r) / len(q), float(np.sqrt(np.mean(r**2))) if len(r) else np.inf
        if len(r) < 6 or fitness < cfg.min_fitness:
            return self._refuse(f"fitness {fitness:.2f}")
        if rmse > cfg.max_rmse:
            return self._refuse(f"rmse {rmse:.4f} m")
        constraint = _constraint(J, q[used])
        if constraint < cfg.min_constraint:
            return self._refuse(f"degenerate: constraint {constraint:.4f}")
        cov = np.linalg.inv(J.T @ J / max(rmse, cfg.depth_sigma) ** 2)
        self.last_reason = ""
        return DenseResult(T_w_ref @ T, T, cov, fitness, rmse, constraint, len(r), (time.perf_counter() - t0) * 1e3)

    def track_frame(self, frame, T_pred: np.ndarray, slam_map, n_features: int):
        """``SlamTracker``'s hook: the frame's dense pose as a ``TrackResult`` (method "dense", no keypoint
        matched to a map point), or None. The reference keyframe's pose is read from ``slam_map`` (local BA
        and loop closing move it after ``set_reference``); a keyframe culled since keeps the pose it had.

        When the frame overlaps the reference less than ``keyframe_fitness``, it becomes the reference itself
        (the step's own, outside the map) and ``wants_keyframe`` asks the tracker for a keyframe here: from
        its keypoints' depth the map gets points where the camera is, so features can take over again.
        ``last_link`` keeps the measured relative pose for the tracker (see ``DenseConfig.link_sigma_deg``)."""
        from vslam.tracking.tracker import TrackResult

        kf = slam_map.keyframes.get(self.ref_id) if self.ref_id is not None else None
        res = self.track(frame.depth, frame.image, T_pred, None if kf is None else kf.T_world_cam)
        self.wants_keyframe = False
        self.last_link = None
        if res is None:
            return None
        chain = self._chain if self._chain is not None and self._chain[0] in slam_map.keyframes else None
        if chain is not None:
            floor = np.r_[np.full(3, np.radians(self.cfg.link_sigma_deg)), np.full(3, self.cfg.link_sigma_m)] ** 2
            k, T_kf_ref, C = chain
            Ad = adjoint(inv_T(res.T_ref_cam))
            self.last_link = (k, T_kf_ref @ res.T_ref_cam, Ad @ C @ Ad.T + res.cov + np.diag(floor))
        if res.fitness < self.cfg.keyframe_fitness:
            self.set_reference(None, res.T_world_cam, frame.depth)
            self._chain = self.last_link
            self.wants_keyframe = True
        return TrackResult(res.T_world_cam, True, np.full(n_features, -1, np.int64), method="dense", cov=res.cov)

    def _refuse(self, reason: str) -> None:
        self.last_reason = reason
        log.debug("dense step refused: %s", reason)
        return None


def _linearize(q: np.ndarray, T_ref_cam: np.ndarray, lvl: _Level,
               dmax: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Point-to-plane rows of the frame points q (N,3, camera frame) at T_ref_cam: (J (M,6), r (M,) metres,
    indices (M,) into q), or None with fewer than 6 correspondences within ``dmax``.

    r = n.(x - p), x = T_ref_cam q, p and n the nearest reference point and its normal. For the update
    T_ref_cam <- T_ref_cam [Exp(w) | v] (so T_cam_ref <- [Exp(-w) | .] T_cam_ref: the left perturbation of
    ``FrameEstimate.pose_cov``, same covariance) x moves by R (w x q + v), so J = [q x m, m], m = R^T n."""
    R, t = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
    x = q @ R.T + t
    dist, idx = lvl.tree.query(x, distance_upper_bound=dmax)  # type: ignore[attr-defined]
    ok = np.flatnonzero(np.isfinite(dist))
    if len(ok) < 6:
        return None
    n = lvl.nrm[idx[ok]]
    r = np.einsum("ij,ij->i", n, x[ok] - lvl.pts[idx[ok]])
    m = n @ R
    return np.concatenate([np.cross(q[ok], m), m], axis=1), r, ok


def _constraint(J: np.ndarray, q: np.ndarray) -> float:
    """Gelfand's stability measure of point-to-plane rows J (M,6) of points q (M,3): the smallest eigenvalue
    of J^T J / M with the rotation columns divided by the points' mean distance (units: m^2 per point)."""
    L = float(np.mean(np.linalg.norm(q, axis=1)))
    Jn = J / np.array([L, L, L, 1.0, 1.0, 1.0])
    return float(np.linalg.eigvalsh(Jn.T @ Jn / len(J))[0])


def _rigid(T: np.ndarray) -> np.ndarray:
    """(4,4) with its rotation block projected onto SO(3) (SVD: the nearest rotation)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
