"""Every tracked frame's pose relative to its reference keyframe, for the final trajectory.

``trajectory.tum.txt`` holds what was known when each frame was tracked. Later events move the keyframes as a
whole -- a loop correction, the monocular visual-inertial initialisation and its refinements (which rescale the
map to metres), the localisation of frames seen before the monocular map existed -- and the frames should follow.
ORB-SLAM's SaveTrajectory does this by storing T_ref_cam per frame; so does ``FrameLog``, and the pipeline writes
``trajectory_final.tum.txt`` (and evaluates it) when ``moved`` says that one of those events happened. A plain
local BA does not set ``moved``: the frames keep their online poses (the numbers every other row reports).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from vslam.geometry.se3 import inv_T

if TYPE_CHECKING:
    from vslam.mapping.map import Map


class FrameLog:
    """Per frame index: (reference keyframe id or None, T_ref_cam -- or T_world_cam when None)."""

    def __init__(self, slam_map: Map):
        self.map = slam_map
        self.archived: dict[int, Map] = {}  # the Atlas's archived maps (its own dict): keyframe ids are unique
        self._rec: dict[int, tuple[int | None, np.ndarray]] = {}
        self.moved = False  # a global change happened after some frames were recorded

    def _keyframe(self, kf_id: int):
        if kf_id in self.map.keyframes:
            return self.map.keyframes[kf_id]
        for m in self.archived.values():
            if kf_id in m.keyframes:
                return m.keyframes[kf_id]
        return None

    def record(self, frame_index: int, ref_kf: int | None, T_world_cam: np.ndarray) -> None:
        T = np.array(T_world_cam, dtype=np.float64)
        if ref_kf is None or ref_kf not in self.map.keyframes:
            self._rec[frame_index] = (None, T)
        else:
            self._rec[frame_index] = (ref_kf, inv_T(self.map.keyframes[ref_kf].T_world_cam) @ T)

    def transform(self, T: np.ndarray, scale: float) -> None:
        """The map moved to x' = T (scale x): relative translations scale, unreferenced poses move."""
        if scale == 1.0 and np.allclose(T, np.eye(4)):
            return
        for k, (ref, P) in self._rec.items():
            Q = P.copy()
            Q[:3, 3] *= scale
            self._rec[k] = (ref, Q if ref is not None else T @ Q)
        self.moved = True

    def scale_refs(self, scales: dict[int, float]) -> None:
        """A monocular (Sim3) loop gave keyframe k the scale ``scales[k]``: its frames' relative translations take it."""
        for k, (ref, P) in self._rec.items():
            if ref is not None and ref in scales and scales[ref] != 1.0:
                Q = P.copy()
                Q[:3, 3] *= scales[ref]
                self._rec[k] = (ref, Q)
        self.moved = True

    def poses(self, frame_indices: list[int]) -> np.ndarray:
        """(F,4,4) T_world_cam of ``frame_indices`` through their reference keyframes' current poses."""
        out = []
        for i in frame_indices:
            ref, P = self._rec[i]
            kf = None if ref is None else self._keyframe(ref)
            out.append(P if kf is None else kf.T_world_cam @ P)
        return np.array(out, dtype=np.float64).reshape(-1, 4, 4)
