"""Dense geometric tracking for RGB-D frames where features are too few (issue 38: white walls, a floor).

When feature tracking fails, the frame's depth is registered against the reference keyframe's: multi-scale
point-to-plane ICP (Chen & Medioni 1992) over a voxel pyramid, started from the motion model's prediction,
optionally coloured ICP (Park, Zhou & Koltun, ICCV 2017) at the finest level. Open3D does the registration.

The covariance and the degeneracy test come from the final point-to-plane correspondences, computed here:
Open3D's ``get_information_matrix_from_point_clouds`` is the point-to-point information, full rank even for
one plane. Geometry alone cannot measure a motion parallel to every visible surface (along a corridor whose
end is out of depth range, across a single wall): such frames are refused, not guessed.

Clouds come from a subsampled depth image (about ``cloud_width`` columns), so one costs a few ms; the
reference keyframe's pyramid (normals, KD-tree) is built on its first use only, since most keyframes are
never needed by this step.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from vslam.data.types import PinholeCamera
from vslam.geometry.se3 import inv_T

log = logging.getLogger(__name__)

# A depth-grid normal is kept when its four neighbours lie within this fraction of the depth from its plane
# (2 cm at 1 m): not across an edge or a depth jump.
_PLANAR_TOL = 0.002
_NORMAL_AGREE = 0.985  # |mean of a voxel's unit normals|: cos 10 deg


@dataclass(frozen=True)
class DenseConfig:
    # On by default: it runs only on RGB-D frames that feature tracking failed, so runs where features track
    # are unchanged, and a frame it cannot measure stays "predicted" as before.
    enabled: bool = True
    cloud_width: int = 80  # the depth image is subsampled to about this many columns (every 4th px at 320x240)
    min_depth: float = 0.2  # metres; depth outside [min, max] is not used
    max_depth: float = 8.0  # beyond, consumer depth sensors are too noisy and sparse
    min_points: int = 500  # valid subsampled depth pixels needed in the frame (and the reference)
    voxel_sizes: tuple[float, ...] = (0.16, 0.08, 0.04)  # metres, coarse to fine; the finest ~ the sample spacing at 3 m
    # correspondence gates, one per level: the coarsest covers the motion model's error after a second or
    # so without features (10-20 cm), the finest only sub-voxel misalignment
    max_correspondence: tuple[float, ...] = (0.3, 0.15, 0.06)
    iterations: tuple[int, ...] = (10, 8, 6)
    # a level stops when fitness and RMS change by less than this (relative); 1e-6 cost 40 % more time for
    # the same poses (to 0.1 mm) on the synthetic room
    rel_tol: float = 1e-4
    # Coloured ICP at the finest level (Open3D's, lambda_geometric 0.968): image gradients on top of the
    # geometry. Off: it recomputes the reference's colour gradients on every call, and where the geometry is
    # degenerate (a corridor) the weak photometric term did not hold the free direction.
    colored: bool = False
    min_fitness: float = 0.5  # share of the frame's points with a reference point within the finest gate
    max_rmse: float = 0.02  # metres, point-to-plane RMS of the inlier correspondences
    # Degeneracy (Gelfand et al. 2003, "Geometrically stable sampling for the ICP algorithm"): the smallest
    # eigenvalue of the point-to-plane information per correspondence, rotations scaled by the mean point
    # distance: how much the weakest direction is constrained per point, 0 for one plane or a corridor seen
    # along its axis. On the synthetic room and corridor, frames at >= 0.002 were within 2.2 mm of the truth
    # and frames at <= 0.0002 were off by 0.1-0.4 m.
    min_constraint: float = 0.001
    # per-point depth noise for the covariance (the measured residual RMS when larger). Neighbouring points'
    # errors are correlated, so the covariance is a lower bound, like the feature tracker's.
    depth_sigma: float = 0.005


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
        self._ref_raw: tuple | None = None  # points (N,3) in the reference camera, intensity (N,), normals (N,3)
        self._ref_levels: list | None = None  # open3d clouds with normals, coarse to fine
        self._ref_tree = None  # scipy cKDTree of the finest level
        self._rays: np.ndarray | None = None
        self.last_reason = ""  # why the last ``track`` returned None (for logs and tests)

    # -- clouds -----------------------------------------------------------------
    def _cloud(self, depth: np.ndarray | None, image: np.ndarray | None,
               normals: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Subsampled back-projection: (N,3) camera-frame points, metres, (N,) intensity in [0,1], and with
        ``normals`` (N,3) unit normals facing the camera (points without one are dropped), else None.

        Normals come from the depth grid (cross product of the neighbours' differences), not from k nearest
        points: far samples along a wall seen at a grazing angle are sparse, and neighbour fits there mixed
        surfaces into normals with a component along a corridor's axis, a constraint that is not there."""
        if depth is None:
            return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)) if normals else None
        s = self.step
        d = np.asarray(depth[::s, ::s], dtype=np.float64)
        if self._rays is None or self._rays.shape[:2] != d.shape:
            v, u = np.mgrid[0 : depth.shape[0] : s, 0 : depth.shape[1] : s]
            uv = self.cam.undistort_points(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
            self._rays = self.cam.backproject(uv, np.ones(len(uv))).reshape(*d.shape, 3)
        ok = np.isfinite(d) & (d > self.cfg.min_depth) & (d < self.cfg.max_depth)
        P = self._rays * np.where(ok, d, np.nan)[..., None]
        nrm = None
        if normals:
            nrm = np.full_like(P, np.nan)
            du, dv = P[1:-1, 2:] - P[1:-1, :-2], P[2:, 1:-1] - P[:-2, 1:-1]
            n = np.cross(du, dv)
            n /= np.linalg.norm(n, axis=-1, keepdims=True)
            c = P[1:-1, 1:-1]
            n *= -np.sign(np.einsum("hwi,hwi->hw", n, c))[..., None]  # towards the camera
            # the four neighbours on the plane through the centre: not across an edge or a depth jump
            dev = np.max([np.abs(np.einsum("hwi,hwi->hw", n, nb - c))
                          for nb in (P[1:-1, 2:], P[1:-1, :-2], P[2:, 1:-1], P[:-2, 1:-1])], axis=0)
            with np.errstate(invalid="ignore"):
                n[~(dev < _PLANAR_TOL * c[..., 2])] = np.nan
            nrm[1:-1, 1:-1] = n
            ok &= np.isfinite(nrm[..., 0])
            nrm = nrm[ok]
        pts = P[ok]
        if image is None:
            return pts, np.zeros(len(pts)), nrm
        img = np.asarray(image[::s, ::s], dtype=np.float64)
        gray = img.mean(axis=2) if img.ndim == 3 else img
        return pts, gray[ok] / 255.0, nrm

    @staticmethod
    def _o3d(pts: np.ndarray, inten: np.ndarray, nrm: np.ndarray | None = None):
        import open3d as o3d

        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(pts)
        pcd.colors = o3d.utility.Vector3dVector(np.repeat(inten[:, None], 3, axis=1))
        if nrm is not None:
            pcd.normals = o3d.utility.Vector3dVector(nrm)
        return pcd

    def set_reference(self, kf_id: int, T_world_cam: np.ndarray, depth: np.ndarray | None, image: np.ndarray | None) -> None:
        """The keyframe later frames are registered against (depth (H,W) float metres, 0 = invalid; image
        (H,W[,3]) uint8): its subsampled cloud is kept, normals and the pyramid are built on first use."""
        self.ref_id, self.T_world_ref = kf_id, np.asarray(T_world_cam, dtype=np.float64).copy()
        self._ref_raw = self._cloud(depth, image, normals=True)
        self._ref_levels = self._ref_tree = None

    def _levels(self) -> list:
        from scipy.spatial import cKDTree

        if self._ref_levels is None:
            pcd = self._o3d(*self._ref_raw)  # type: ignore[misc]
            levels = []
            for v in self.cfg.voxel_sizes:
                down = pcd.voxel_down_sample(v)  # points and normals averaged per voxel
                # A voxel across two surfaces (where a wall meets the ceiling) gets a point between them and
                # a normal of neither; a few % of such points held ICP 1-2 cm off in the corridor. Their mean
                # normal is short: keep the voxels whose normals agree within ~10 degrees.
                keep = np.flatnonzero(np.linalg.norm(np.asarray(down.normals), axis=1) > _NORMAL_AGREE)
                down = down.select_by_index(keep)
                down.normalize_normals()
                levels.append(down)
            self._ref_levels, self._ref_tree = levels, cKDTree(np.asarray(levels[-1].points))
        return self._ref_levels

    # -- tracking ---------------------------------------------------------------
    def track(self, depth: np.ndarray | None, image: np.ndarray | None, T_pred: np.ndarray,
              T_world_ref: np.ndarray | None = None) -> DenseResult | None:
        """Pose of the frame from the prediction T_pred (4,4 T_world_cam); ``T_world_ref``: the reference
        keyframe's current pose (local BA moves it; None = as given to ``set_reference``). None when the
        result is not trustworthy (``last_reason`` says why)."""
        import open3d as o3d

        t0 = time.perf_counter()
        cfg = self.cfg
        reg = o3d.pipelines.registration
        if self._ref_raw is None or len(self._ref_raw[0]) < cfg.min_points:
            return self._refuse("reference keyframe has too few depth points")
        pts, inten, _ = self._cloud(depth, image)
        if len(pts) < cfg.min_points:
            return self._refuse(f"{len(pts)} depth points")
        T_w_ref = self.T_world_ref if T_world_ref is None else np.asarray(T_world_ref, dtype=np.float64)
        # T_ref_cam, refined level by level. ICP composes rigid updates onto the start, so a start that is not
        # quite a rotation stays so, and through the motion model (velocity = inv_T(T_prev) @ T) that error doubled
        # with every frame tracked here: re-orthonormalised
        T = _rigid(inv_T(T_w_ref) @ np.asarray(T_pred, dtype=np.float64))
        src = self._o3d(pts, inten)
        levels = self._levels()
        for i, (tgt, v, dmax, iters) in enumerate(zip(levels, cfg.voxel_sizes, cfg.max_correspondence, cfg.iterations)):
            down = src.voxel_down_sample(v)
            crit = reg.ICPConvergenceCriteria(relative_fitness=cfg.rel_tol, relative_rmse=cfg.rel_tol, max_iteration=int(iters))
            # Tukey at the voxel size: where two surfaces meet, normals are mixed and residuals of cm
            kernel = reg.TukeyLoss(k=v)
            if cfg.colored and i == len(levels) - 1:
                est = reg.TransformationEstimationForColoredICP(0.968, kernel)
                r = reg.registration_colored_icp(down, tgt, dmax, T, est, crit)
            else:
                r = reg.registration_icp(down, tgt, dmax, T, reg.TransformationEstimationPointToPlane(kernel), crit)
            T = _rigid(np.asarray(r.transformation, dtype=np.float64))
        stats = self._information(np.asarray(down.points), T, levels[-1], cfg.max_correspondence[-1])
        if stats is None:
            return self._refuse("no correspondences")
        H, n_corr, rmse, constraint = stats
        fitness = n_corr / len(down.points)
        if fitness < cfg.min_fitness:
            return self._refuse(f"fitness {fitness:.2f}")
        if rmse > cfg.max_rmse:
            return self._refuse(f"rmse {rmse:.4f} m")
        if constraint < cfg.min_constraint:
            return self._refuse(f"degenerate: constraint {constraint:.4f}")
        self.last_reason = ""
        ms = (time.perf_counter() - t0) * 1e3
        return DenseResult(T_w_ref @ T, T, np.linalg.inv(H), fitness, rmse, constraint, n_corr, ms)

    def track_frame(self, frame, T_pred: np.ndarray, slam_map, n_features: int):
        """``SlamTracker``'s hook: the frame's dense pose as a ``TrackResult`` (method "dense", no keypoint
        matched to a map point), or None. The reference keyframe's pose is read from ``slam_map`` (local BA
        and loop closing move it after ``set_reference``); a keyframe culled since keeps the pose it had."""
        from vslam.tracking.tracker import TrackResult

        kf = slam_map.keyframes.get(self.ref_id) if self.ref_id is not None else None
        res = self.track(frame.depth, frame.image, T_pred, None if kf is None else kf.T_world_cam)
        if res is None:
            return None
        return TrackResult(res.T_world_cam, True, np.full(n_features, -1, np.int64), method="dense", cov=res.cov)

    def _refuse(self, reason: str) -> None:
        self.last_reason = reason
        log.debug("dense step refused: %s", reason)
        return None

    def _information(self, q: np.ndarray, T_ref_cam: np.ndarray, tgt, dmax: float) -> tuple[np.ndarray, int, float, float] | None:
        """Point-to-plane information of the pose at T_ref_cam: (H (6,6), inlier count, RMS metres, constraint).

        q: (N,3) frame points, camera frame. Residual r = n.(x - p), x = T_ref_cam q, p and n the nearest
        reference point and its normal. Under the left perturbation T_cam_ref <- [Exp(w) | v] T_cam_ref (that
        of ``FrameEstimate.pose_cov``) x moves by -R (w x q + v), so a row's Jacobian is -[q x m, m], m = R^T n;
        H = J^T J / sigma^2. ``constraint``: smallest eigenvalue of J^T J / N with q scaled by 1 / mean |q|."""
        R, t = T_ref_cam[:3, :3], T_ref_cam[:3, 3]
        x = q @ R.T + t
        dist, idx = self._ref_tree.query(x, distance_upper_bound=dmax)  # type: ignore[union-attr]
        ok = np.flatnonzero(np.isfinite(dist))
        if len(ok) < 6:
            return None
        nrm = np.asarray(tgt.normals)[idx[ok]]
        r = np.einsum("ij,ij->i", nrm, x[ok] - np.asarray(tgt.points)[idx[ok]])
        # inliers within 3 robust sigmas (MAD): where two surfaces meet, normals are mixed and residuals of cm
        scale = max(1.4826 * float(np.median(np.abs(r))), self.cfg.depth_sigma / 3)
        inl = np.abs(r) <= 3.0 * scale
        if inl.sum() < 6:
            return None
        ok, nrm, r = ok[inl], nrm[inl], r[inl]
        m = nrm @ R
        qc = q[ok]
        J = np.concatenate([np.cross(qc, m), m], axis=1)
        rmse = float(np.sqrt(np.mean(r**2)))
        L = float(np.mean(np.linalg.norm(qc, axis=1)))
        Jn = J / np.array([L, L, L, 1.0, 1.0, 1.0])
        constraint = float(np.linalg.eigvalsh(Jn.T @ Jn / len(ok))[0])
        H = J.T @ J / max(rmse, self.cfg.depth_sigma) ** 2
        return H, len(ok), rmse, constraint


def _rigid(T: np.ndarray) -> np.ndarray:
    """(4,4) with its rotation block projected onto SO(3) (SVD, nearest in Frobenius norm)."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
