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
