"""A BA window as dense numpy arrays (ids -> indices, measurements, chi2 thresholds); no GTSAM here."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from vslam.backend.projection import chi2_thresholds, measurement_matrix, whitened_sq_errors
from vslam.geometry.se3 import gather_Rt, inv_T

if TYPE_CHECKING:
    from vslam.backend.ba import BackendConfig, BAProblem, StereoCamera


@dataclass
class DenseWindow:
    """K keyframes, P points, M observations of a ``BAProblem``.

    kf_ids (K,), pt_ids (P,): sorted ids; Twc0 (K,4,4) T_world_cam and P0 (P,3) world metres: initial guess.
    kf, pt (M,): ids of each observation; ik, ip (M,): their indices into kf_ids / pt_ids;
    meas (M,3): uL, v, uR pixels (uR 0 for mono); stereo (M,) bool; sigma (M,) px (NaN if <= 0);
    thr (M,): chi2 threshold (chi2_mono or chi2_stereo).
    """

    kf_ids: np.ndarray
    pt_ids: np.ndarray
    Twc0: np.ndarray
    P0: np.ndarray
    kf: np.ndarray
    pt: np.ndarray
    ik: np.ndarray
    ip: np.ndarray
    meas: np.ndarray
    stereo: np.ndarray
    sigma: np.ndarray
    thr: np.ndarray

    def chi2(self, Twc: np.ndarray, P: np.ndarray, camera: StereoCamera) -> np.ndarray:
        """(M,) unrobust whitened squared errors at poses Twc (K,4,4) and points P (P,3); inf = NaN or behind."""
        return self._chi2(Twc, P, camera, self.stereo)

    def uv_chi2(self, Twc: np.ndarray, P: np.ndarray, camera: StereoCamera) -> np.ndarray:
        """(M,) as ``chi2`` from the left-image pixel (uL, v) alone: is the match right when the depth is not?"""
        return self._chi2(Twc, P, camera, np.zeros_like(self.stereo))

    def _chi2(self, Twc: np.ndarray, P: np.ndarray, camera: StereoCamera, stereo: np.ndarray) -> np.ndarray:
        if self.kf.shape[0] == 0:
            return np.zeros(0)
        Tcw = inv_T(Twc)
        R, t = gather_Rt(Tcw, self.ik)
        pc = np.einsum("mij,mj->mi", R, P[self.ip]) + t
        chi2, _ = whitened_sq_errors(pc, self.meas, stereo, self.sigma, camera)
        return chi2


def dense_window(problem: BAProblem, camera: StereoCamera, cfg: BackendConfig) -> DenseWindow:
    """Problem -> DenseWindow. Raises ValueError if an observation names an unknown keyframe or point id."""
    kf_ids = np.array(sorted(problem.poses), dtype=np.int64)
    pt_ids, P0 = _sorted_points(problem.points)
    kf = np.asarray(problem.obs_kf, dtype=np.int64).reshape(-1)
    pt = np.asarray(problem.obs_pt, dtype=np.int64).reshape(-1)
    m = kf.shape[0]
    ik, ok_k = _lookup(kf_ids, kf)
    ip, ok_p = _lookup(pt_ids, pt)
    if not (ok_k.all() and ok_p.all()):
        raise ValueError(
            f"BAProblem observations name unknown keyframes {sorted(set(kf[~ok_k].tolist()))} "
            f"or points {sorted(set(pt[~ok_p].tolist()))}"
        )
    meas, stereo = measurement_matrix(np.asarray(problem.obs_uv).reshape(m, 2), np.asarray(problem.obs_ur).reshape(m))
    if camera.baseline <= 0:
        stereo[:] = False  # no baseline: ur means nothing
    sigma = np.full(m, cfg.pixel_sigma)
    if problem.obs_sigma is not None:
        sigma = np.asarray(problem.obs_sigma, dtype=np.float64).reshape(m)
    Twc0 = np.zeros((kf_ids.size, 4, 4))
    for i, k in enumerate(kf_ids.tolist()):
        Twc0[i] = problem.poses[k]
    return DenseWindow(
        kf_ids, pt_ids, Twc0, P0, kf, pt, ik, ip, meas, stereo,
        np.where(sigma > 0, sigma, np.nan), chi2_thresholds(stereo, cfg.chi2_mono, cfg.chi2_stereo),
    )


def _sorted_points(points: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(P,) sorted point ids and (P,3) their positions. Local mapping hands the points in id order: then one
    array of the dict's values, no lookup per id."""
    ids = np.fromiter(points.keys(), np.int64, len(points))
    xyz = np.array(list(points.values()), dtype=np.float64).reshape(-1, 3)
    if ids.size > 1 and not (ids[1:] > ids[:-1]).all():
        order = np.argsort(ids)
        ids, xyz = ids[order], xyz[order]
    return ids, xyz


def _lookup(sorted_ids: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of query ids in sorted_ids, and whether each one is there."""
    idx = np.searchsorted(sorted_ids, query)
    ok = idx < sorted_ids.size
    ok[ok] = sorted_ids[idx[ok]] == query[ok]
    return np.where(ok, idx, 0), ok
