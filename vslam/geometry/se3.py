"""Rigid-body helpers on 4x4 homogeneous matrices.

Convention everywhere in vslam: ``T_a_b`` maps points from frame b to frame a,
``p_a = T_a_b @ p_b``. Quaternions are Hamilton, stored (w, x, y, z) unless a
name says ``xyzw`` (the TUM file order).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3,3) rotation and (3,) translation -> (4,4) float64 transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (or a stack (N,4,4)) without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def gather_Rt(T: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,4,4) transforms and (M,) indices -> their rotations (M,3,3) and translations (M,3). ``np.take`` of
    contiguous copies: the same values as ``T[idx, :3, :3]``, whose mixed fancy + slice indexing is ~5-10x
    slower (the per-observation gathers of the BA windows' inner loops)."""
    return (np.take(np.ascontiguousarray(T[:, :3, :3]), idx, axis=0),
            np.take(np.ascontiguousarray(T[:, :3, 3]), idx, axis=0))


def quat_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotations; normalises the input."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 4) quaternions (w, x, y, z) with w >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0, -q, q)


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3,3) cross-product matrix."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (radians) -> (..., 3, 3) rotations."""
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (radians)."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def interpolate_poses(t: np.ndarray, T: np.ndarray, known: np.ndarray, group: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N,4,4) at times ``t`` (increasing) where ``known`` is False replaced by the interpolation between the
    nearest known poses before and after them (rotation by slerp, position linearly in time) -- only where both
    exist and share the ``group`` (e.g. the map) of the pose replaced. -> (poses, mask of the poses replaced)."""
    from scipy.spatial.transform import Slerp

    t, known = np.asarray(t, np.float64), np.asarray(known, bool)
    group = np.zeros(len(t), np.int64) if group is None else np.asarray(group)
    out, done = np.array(T, dtype=np.float64, copy=True), np.zeros(len(t), bool)
    idx = np.flatnonzero(known)
    if len(idx) < 2:
        return out, done
    for i in np.flatnonzero(~known):
        k = np.searchsorted(idx, i)
        if k == 0 or k == len(idx):
            continue
        a, b = idx[k - 1], idx[k]
        if not group[a] == group[b] == group[i]:
            continue
        w = (t[i] - t[a]) / (t[b] - t[a])
        rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T[a, :3, :3], T[b, :3, :3]])))([w]).as_matrix()[0]
        out[i, :3, :3] = rot
        out[i, :3, 3] = (1 - w) * T[a, :3, 3] + w * T[b, :3, 3]
        done[i] = True
    return out, done
