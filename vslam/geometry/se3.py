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
    contiguous copies: the same values as ``T[idx, :3, :3]``, whose mixed fancy + slice indexing is much
    slower (docs/speed.md; the per-observation gathers of the BA windows' inner loops)."""
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


def adjoint(T: np.ndarray) -> np.ndarray:
    """(6,6) adjoint of T in (rotation, translation) order, as GTSAM's ``Pose3.AdjointMap``: T Exp(x) = Exp(Ad x) T.
    Compounding A B with right perturbations of both, A's error reaches the product through adjoint(B^-1)."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = Ad[3:, 3:] = R
    Ad[3:, :3] = skew(np.asarray(T, dtype=np.float64)[:3, 3]) @ R
    return Ad


def so3_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (radians) -> (..., 3, 3) rotations."""
    return Rotation.from_rotvec(np.asarray(w, dtype=np.float64)).as_matrix()


def so3_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of one rotation (3,3), from its trace."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (radians)."""
    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def interpolate_poses(t: np.ndarray, T: np.ndarray, known: np.ndarray, group: np.ndarray | None = None,
                      tangent_window: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N,4,4) at times ``t`` (increasing) where ``known`` is False replaced by the interpolation between the
    nearest known poses before and after them -- only where both exist and share the ``group`` (e.g. the map) of
    the pose replaced. -> (poses, mask of the poses replaced).

    Rotation by slerp (exact for a constant turn rate). Position by a cubic Hermite curve whose end velocities are
    the known motion within ``tangent_window`` seconds outside the gap (the camera does not stop at a gap's ends:
    a linear chord across a 3 s gap of a turning camera cuts the curve by decimetres); linear where an end has no
    such motion. The window spans several frames so that one frame's pose noise does not set the tangent."""
    from scipy.spatial.transform import Slerp

    t, known = np.asarray(t, np.float64), np.asarray(known, bool)
    group = np.zeros(len(t), np.int64) if group is None else np.asarray(group)
    out, done = np.array(T, dtype=np.float64, copy=True), np.zeros(len(t), bool)
    idx = np.flatnonzero(known)
    if len(idx) < 2:
        return out, done

    def velocity(k: int, step: int) -> np.ndarray | None:
        """Velocity at known pose idx[k] from the known poses of its group within the window on the side away
        from the gap (step -1: before, +1: after): the slope at idx[k] of a least-squares quadratic (a mean
        velocity would lag a turning camera's by half the window)."""
        js = [idx[k]]
        while 0 <= k + step * len(js) < len(idx) and group[idx[k + step * len(js)]] == group[idx[k]] \
                and abs(t[idx[k + step * len(js)]] - t[idx[k]]) <= tangent_window:
            js.append(idx[k + step * len(js)])
        if len(js) < 2:
            return None
        dts, P = t[js] - t[idx[k]], T[js, :3, 3]
        if len(js) == 2:
            return (P[1] - P[0]) / dts[1]
        A = np.stack([np.ones_like(dts), dts, dts**2], axis=1)
        return np.linalg.lstsq(A, P, rcond=None)[0][1]

    for i in np.flatnonzero(~known):
        k = np.searchsorted(idx, i)
        if k == 0 or k == len(idx):
            continue
        a, b = idx[k - 1], idx[k]
        if not group[a] == group[b] == group[i]:
            continue
        dt = t[b] - t[a]
        w = (t[i] - t[a]) / dt
        rot = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T[a, :3, :3], T[b, :3, :3]])))([w]).as_matrix()[0]
        out[i, :3, :3] = rot
        pa, pb = T[a, :3, 3], T[b, :3, 3]
        va, vb = velocity(k - 1, -1), velocity(k, +1)
        if va is None or vb is None:
            out[i, :3, 3] = (1 - w) * pa + w * pb
        else:
            h00, h10, h01, h11 = 2 * w**3 - 3 * w**2 + 1, w**3 - 2 * w**2 + w, -2 * w**3 + 3 * w**2, w**3 - w**2
            out[i, :3, 3] = h00 * pa + h10 * dt * va + h01 * pb + h11 * dt * vb
        done[i] = True
    return out, done
