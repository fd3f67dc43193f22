"""Analytic ray casting of the synthetic scene in vectorised numpy.

Each pixel's ray is precomputed once in the camera frame as ((u-cx)/fx,
(v-cy)/fy, 1), so the ray parameter of a hit *is* its depth (z along the
optical axis) and depth maps are exact. Per view:

1. the exit distance through the static box, min over axes of the positive
   wall distances (the camera is always inside it);
2. each mover by the slab test, only inside the image window its projected
   corners cover, keeping the nearer hit (z-buffer);
3. hit points -> face (s, r) metres -> texture atlas coordinates, and one
   ``cv2.remap`` (bilinear) produces the colour image.

Speed (measured in docs/data.md, "Synthetic rendering speed"): about half of a
frame's time is the two ``cv2.remap`` calls and the box trace; movers cost little
because they are traced only inside their projected windows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vslam.data.synthetic.scene import FACE_AXES, Mover, Scene
from vslam.data.types import PinholeCamera


@dataclass
class View:
    """One rendered view. image: (H,W,3) uint8 BGR; depth: (H,W) float32 metres along the
    optical axis (> 0 everywhere: the scene is closed); obj: (H,W) uint8, 0 static, i+1
    where mover i is the front-most surface."""

    image: np.ndarray
    depth: np.ndarray
    obj: np.ndarray


class Renderer:
    """Renders ``scene`` through ``camera`` (pinhole, no distortion) from any pose."""

    def __init__(self, scene: Scene, camera: PinholeCamera):
        self.scene = scene
        self.camera = camera
        u = (np.arange(camera.width, dtype=np.float64) - camera.cx) / camera.fx
        v = (np.arange(camera.height, dtype=np.float64) - camera.cy) / camera.fy
        uu, vv = np.meshgrid(u, v)
        self._rays = np.stack([uu, vv, np.ones_like(uu)]).astype(np.float32).reshape(3, -1)
        # Per static face: atlas position of texel (0,0) shifted by the box corner and the
        # half texel of the pixel-centre convention, so map = table[face] + coord * ppm.
        ppm = scene.ppm
        self._face_x = np.zeros(6, np.float32)
        self._face_y = np.zeros(6, np.float32)
        for f in range(6):
            sa, ra = FACE_AXES[f // 2]
            self._face_x[f] = scene.face_x[f] - scene.lo[sa] * ppm - 0.5
            self._face_y[f] = scene.face_y[f] - scene.lo[ra] * ppm - 0.5

    def render(self, T_world_cam: np.ndarray, tau: float, movers: bool = True) -> View:
        """Render from pose T_world_cam (4,4) at time tau (s since frame 0, positions the movers)."""
        h, w = self.camera.height, self.camera.width
        C = T_world_cam[:3, 3].astype(np.float64)
        D = (T_world_cam[:3, :3].astype(np.float32) @ self._rays).reshape(3, h, w)
        t, face = self._trace_box(C, D)
        mapx, mapy = self._static_maps(C, D, t, face)
        obj = np.zeros((h, w), np.uint8)
        if movers:
            for i, m in enumerate(self.scene.movers):
                self._trace_mover(i + 1, m, tau, T_world_cam, C, D, t, obj, mapx, mapy)
        image = cv2.remap(self.scene.atlas, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return View(image, t, obj)

    def _trace_box(self, C: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exit distance (H,W) float32 and face index (H,W) uint8 from inside the static box."""
        lo, hi = self.scene.lo - C, self.scene.hi - C
        ts = []
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                # signbit, not D < 0: a ray with D = +0 or -0 must get +inf, never -inf.
                neg = np.signbit(D[k])
                ts.append((np.where(neg, np.float32(lo[k]), np.float32(hi[k])) / D[k], neg.view(np.uint8)))
        (tx, nx), (ty, ny), (tz, nz) = ts
        t = np.minimum(np.minimum(tx, ty), tz)
        one, three, five = np.uint8(1), np.uint8(3), np.uint8(5)
        face = np.where(tx == t, one - nx, np.where(ty == t, three - ny, five - nz))
        return t, face

    def _static_maps(self, C: np.ndarray, D: np.ndarray, t: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Atlas coordinates (H,W) float32 of the static hit points."""
        ppm = np.float32(self.scene.ppm)
        tp = t * ppm
        px = np.float32(C[0] * ppm) + tp * D[0]  # texels from the world origin
        py = np.float32(C[1] * ppm) + tp * D[1]
        pz = np.float32(C[2] * ppm) + tp * D[2]
        s = np.where(face < 2, py, px)  # the face's s axis: y on x-faces, else x
        r = np.where(face >= 4, py, pz)  # the face's r axis: y on z-faces, else z
        s += self._face_x[face]
        r += self._face_y[face]
        return s, r

    def _window(self, lo: np.ndarray, hi: np.ndarray, T_world_cam: np.ndarray) -> tuple[slice, slice] | None:
        """Image rows/cols the box can cover (from its projected corners), None when it cannot be seen."""
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
        pc = (corners - C) @ R  # camera frame: R^T (p - C)
        cam = self.camera
        if np.all(pc[:, 2] <= 1e-6):
            return None
        if np.any(pc[:, 2] <= 1e-3):  # straddles the camera plane: projections are unbounded
            return slice(0, cam.height), slice(0, cam.width)
        uv = cam.project(pc)
        x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        x0, x1 = max(x0, 0), min(x1, cam.width)
        y0, y1 = max(y0, 0), min(y1, cam.height)
        if x0 >= x1 or y0 >= y1:
            return None
        return slice(y0, y1), slice(x0, x1)

    def _trace_mover(
        self, oid: int, m: Mover, tau: float, T_world_cam: np.ndarray, C: np.ndarray, D: np.ndarray,
        t: np.ndarray, obj: np.ndarray, mapx: np.ndarray, mapy: np.ndarray,
    ) -> None:
        """Slab test of mover ``oid``; updates the z-buffer ``t``, ``obj`` and the atlas maps in place."""
        lo_w, hi_w = m.bounds(tau)
        win = self._window(lo_w, hi_w, T_world_cam)
        if win is None:
            return
        Dw = [D[k][win] for k in range(3)]
        tmins, tmaxs = [], []
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                inv = np.float32(1.0) / Dw[k]
                t1, t2 = np.float32(lo_w[k] - C[k]) * inv, np.float32(hi_w[k] - C[k]) * inv
                tmins.append(np.minimum(t1, t2))
                tmaxs.append(np.maximum(t1, t2))
            tnear = np.maximum(np.maximum(tmins[0], tmins[1]), tmins[2])
            tfar = np.minimum(np.minimum(tmaxs[0], tmaxs[1]), tmaxs[2])
            tw = t[win]
            hit = (tnear <= tfar) & (tnear > 0) & (tnear < tw)
        if not hit.any():
            return
        th = tnear[hit]
        k = np.where(tmins[0][hit] == th, 0, np.where(tmins[1][hit] == th, 1, 2))
        d_hit = [Dw[a][hit] for a in range(3)]
        rel = [np.float32(C[a] - lo_w[a]) + th * d_hit[a] for a in range(3)]  # metres from the box's lo corner
        d_k = np.choose(k, d_hit)
        face = 2 * k + (d_k < 0)  # a ray travelling towards -k enters through the hi face
        s = np.where(k == 0, rel[1], rel[0])
        r = np.where(k == 2, rel[1], rel[2])
        ppm = np.float32(self.scene.ppm)
        tw[hit] = th
        obj[win][hit] = oid
        mapx[win][hit] = m.face_x[face].astype(np.float32) - 0.5 + s * ppm
        mapy[win][hit] = m.face_y[face].astype(np.float32) - 0.5 + r * ppm


def boxes_from_ids(obj: np.ndarray, n_movers: int) -> tuple[np.ndarray, np.ndarray]:
    """Tight boxes of each visible mover: ((K,4) float64 x1,y1,x2,y2 inclusive pixel indices, (K,) ids 0-based)."""
    boxes, ids = [], []
    if not obj.any():
        return np.zeros((0, 4)), np.zeros(0, np.int64)
    for i in range(n_movers):
        m = obj == i + 1
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        if len(rows):
            boxes.append((cols[0], rows[0], cols[-1], rows[-1]))
            ids.append(i)
    return np.array(boxes, dtype=np.float64).reshape(-1, 4), np.array(ids, dtype=np.int64)
