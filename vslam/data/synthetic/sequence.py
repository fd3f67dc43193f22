"""SyntheticSequence: a seeded, deterministic Sequence with exact ground truth.

Building one computes the motion and IMU; the scene and its textures (well
under a second at the default size) are made at the first frame rendered,
and frames are ray cast lazily when iterated.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from dataclasses import dataclass
from typing import Iterator

import cv2
import numpy as np

from vslam.data.synthetic.config import SyntheticConfig
from vslam.data.synthetic.imu import ImuTruth, imu_grid_us, microsecond_grid, synthesize_imu
from vslam.data.synthetic.motion import RigMotion, build_motion
from vslam.data.synthetic.render import Renderer, boxes_from_ids
from vslam.data.synthetic.scene import Scene, build_scene
from vslam.data.trajectory import Trajectory
from vslam.data.types import Calibration, Frame, ImuSamples, PinholeCamera, Sequence, SensorKind
from vslam.geometry.se3 import make_T

logger = logging.getLogger(__name__)

DEPTH_SCALE = 5000.0  # raw units per metre in the written depth PNGs (TUM convention)


@dataclass
class SyntheticRender:
    """Everything rendered for one frame.

    image, right: (H,W,3) uint8 BGR (right is None when not asked for).
    depth: (H,W) float32 metres along cam0's optical axis, 0 on blacked-out frames.
    mask: (H,W) bool, True exactly where a mover is the front-most surface.
    boxes: (K,4) float64 x1,y1,x2,y2, inclusive pixel bounds of each visible mover's
    mask; box_ids: (K,) int64 mover index (0-based) of each box.
    T_world_cam: (4,4) ground-truth pose of cam0.
    """

    image: np.ndarray
    depth: np.ndarray
    right: np.ndarray | None
    mask: np.ndarray
    boxes: np.ndarray
    box_ids: np.ndarray
    T_world_cam: np.ndarray


def default_name(cfg: SyntheticConfig) -> str:
    flags = "".join(f"_{f}" for f in ("loop", "low_texture", "lighting_change") if getattr(cfg, f))
    flags += "_poor_light" if cfg.exposure != 1.0 or cfg.image_noise > 0 else ""
    return f"synthetic_{cfg.scene}{flags}_seed{cfg.seed}"


class SyntheticSequence(Sequence):
    """Procedural room or street seen by a stereo RGB-D camera on an IMU rig.

    cfg: what to generate (``SyntheticConfig()`` when None).
    sensor: what the sequence reports as ``sensor``; frames always carry the
        colour image and depth, and the right image only for "stereo" (it
        doubles the render time; ``render(i, right=True)`` gives it anyway).
    Frames: BGR uint8 images, depth in metres, ``imu`` = samples in
    (previous frame's t, t] (the first frame: (t0 - one IMU period, t0], as
    the EuRoC reader does), ground-truth T_world_cam of cam0, dynamic mask and
    mover boxes.
    """

    def __init__(self, cfg: SyntheticConfig | None = None, sensor: SensorKind = "rgbd", name: str | None = None):
        if sensor not in ("rgbd", "stereo", "mono"):
            raise ValueError(f"sensor must be 'rgbd', 'stereo' or 'mono', got {sensor!r}")
        self.cfg = cfg = cfg if cfg is not None else SyntheticConfig()
        self.sensor = sensor
        self.name = name or default_name(cfg)
        frame_us = microsecond_grid(cfg.n_frames, cfg.fps)
        self._tau = frame_us * 1e-6
        self._t = cfg.start_time + self._tau
        start_ns = int(round(cfg.start_time * 1e9))
        self._ns = start_ns + frame_us * 1000
        self.motion: RigMotion = build_motion(cfg)
        cx, cy = cfg.principal_point
        cam = PinholeCamera(cfg.width, cfg.height, cfg.fx, cfg.fy, cx, cy)
        self.T_cam0_cam1 = make_T(np.eye(3), np.array([cfg.baseline, 0.0, 0.0]))
        T_b_c0 = self.motion.T_body_cam0
        self.calibration = Calibration(
            cam0=cam,
            cam1=cam,
            T_body_cam0=T_b_c0.copy(),
            T_body_cam1=T_b_c0 @ self.T_cam0_cam1,
            imu=dataclasses.replace(cfg.imu_noise, rate_hz=cfg.imu_rate),
            depth_scale=DEPTH_SCALE,
        )
        self._T_wc0 = self.motion.T_world_cam0(self._tau)
        self._scene: Scene | None = None  # built on first use (``scene``)
        self._renderer: Renderer | None = None
        self._room2: tuple[Scene, Renderer] | None = None  # cfg.second_room's scene, built on first use
        imu_us = imu_grid_us(cfg, int(frame_us[-1]))
        self._imu_ns = start_ns + imu_us * 1000
        self._imu, self._imu_truth = synthesize_imu(cfg, self.motion, imu_us)
        self._blackout = np.zeros(cfg.n_frames, bool)
        for start, length in cfg.blackouts:
            self._blackout[start : start + length] = True
        self._blur = np.zeros(cfg.n_frames, bool)
        for start, length in cfg.blurs:
            self._blur[start : start + length] = True
        self._fade = np.zeros(cfg.n_frames, bool)
        for start, length in cfg.fades:
            self._fade[start : start + length] = True
        rng = np.random.default_rng([cfg.seed, 4])  # stream 4: lighting
        self._light = (rng.uniform(3.0, 5.0), rng.uniform(0, 2 * np.pi), rng.uniform(5.0, 8.0), rng.uniform(0, 2 * np.pi))

    @property
    def scene(self) -> Scene:
        """The static box, its texture atlas and the movers, built when first needed: a long street's atlas is
        hundreds of MB, and a process that renders no frame (the tracking process, when the front end runs in a
        child) then never holds it."""
        if self._scene is None:
            self._scene, self._renderer = self._build_scene(self.cfg)
            logger.debug("%s: %d frames, %d IMU samples, %d movers, atlas %s", self.name, len(self), len(self._imu),
                         len(self._scene.movers), self._scene.atlas.shape)
        return self._scene

    def __getstate__(self) -> dict:
        """Pickled without the scene: it is a function of ``cfg`` (seeded), so the receiver builds the same bytes
        if it renders, and a sequence sent to a child process is a few MB instead of the atlas's hundreds."""
        state = self.__dict__.copy()
        state["_scene"] = state["_renderer"] = state["_room2"] = None
        return state

    # ------------------------------------------------------------------ Sequence interface

    def __len__(self) -> int:
        return self.cfg.n_frames

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def groundtruth(self) -> Trajectory:
        """cam0 poses T_world_cam at the frame times."""
        return Trajectory(self._t.copy(), self._T_wc0.copy())

    def imu(self) -> ImuSamples:
        return ImuSamples(self._imu.t.copy(), self._imu.gyro.copy(), self._imu.accel.copy())

    # ------------------------------------------------------------------ extras

    def timestamps_ns(self) -> np.ndarray:
        """(N,) int64 frame times in nanoseconds (exact; whole microseconds)."""
        return self._ns.copy()

    def imu_timestamps_ns(self) -> np.ndarray:
        """(M,) int64 IMU sample times in nanoseconds (exact; whole microseconds)."""
        return self._imu_ns.copy()

    def imu_truth(self) -> ImuTruth:
        """True state and biases at every IMU sample (the test oracle for inertial code); a copy."""
        return copy.deepcopy(self._imu_truth)

    def landmarks(self) -> np.ndarray:
        """(M,3) world points, metres: centres of the dark marker dots painted on the static faces."""
        return self.scene.landmarks.copy()

    def blackout_frames(self) -> np.ndarray:
        """(K,) int indices of the frames rendered all black."""
        return np.flatnonzero(self._blackout)

    def frame_imu(self, i: int) -> ImuSamples:
        t0 = self._t[i - 1] if i > 0 else self._t[0] - 1.0 / self.cfg.imu_rate
        return self._imu.between(t0, self._t[i])

    def frame(self, i: int) -> Frame:
        # The right image doubles the render cost: only a stereo sequence pays for it.
        r = self.render(i, right=self.sensor == "stereo")
        return Frame(
            index=i,
            timestamp=float(self._t[i]),
            image=r.image,
            depth=r.depth,
            right=r.right,
            imu=self.frame_imu(i),
            T_world_cam=r.T_world_cam,
            dynamic_mask=r.mask,
            boxes=r.boxes,
        )

    def render(self, i: int, movers: bool = True, right: bool = True) -> SyntheticRender:
        """Render frame i; ``movers=False`` renders the static scene only (the mask oracle)."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range 0..{len(self) - 1}")
        cfg, T = self.cfg, self._T_wc0[i].copy()
        if self._blackout[i]:
            black = np.zeros((cfg.height, cfg.width, 3), np.uint8)
            return SyntheticRender(
                black, np.zeros((cfg.height, cfg.width), np.float32), black.copy() if right else None,
                np.zeros((cfg.height, cfg.width), bool), np.zeros((0, 4)), np.zeros(0, np.int64), T,
            )
        tau = float(self._tau[i])
        scene, renderer = self._scene_at(i)
        left = renderer.render(T, tau, movers)
        lut = self._lighting_lut(i)
        image = self._sensor(i, 0, self._faded(i, self._blurred(i, cv2.LUT(left.image, lut) if lut is not None else left.image)))
        right_img = None
        if right:
            view = renderer.render(T @ self.T_cam0_cam1, tau, movers)
            right_img = self._sensor(i, 1, self._faded(i, self._blurred(i, cv2.LUT(view.image, lut) if lut is not None else view.image)))
        boxes, ids = boxes_from_ids(left.obj, len(scene.movers))
        return SyntheticRender(image, left.depth, right_img, left.obj > 0, boxes, ids, T)

    def _scene_at(self, i: int) -> tuple[Scene, Renderer]:
        """The scene frame ``i`` is rendered in, and its renderer: the second room from ``cfg.second_room`` on."""
        scene = self.scene
        assert self._renderer is not None  # built with the scene
        if not self.cfg.second_room or i < self.cfg.second_room:
            return scene, self._renderer
        if self._room2 is None:
            self._room2 = self._build_scene(dataclasses.replace(self.cfg, seed=self.cfg.seed + 1))
        return self._room2

    def _build_scene(self, cfg: SyntheticConfig) -> tuple[Scene, Renderer]:
        """The scene of ``cfg`` around this sequence's camera path (both cameras' centres), and its renderer."""
        T = self._T_wc0
        centres = np.stack([T[:, :3, 3], (T @ self.T_cam0_cam1)[:, :3, 3]], axis=1)
        scene = build_scene(cfg, centres, self._tau)
        return scene, Renderer(scene, self.calibration.cam0)

    def _blurred(self, i: int, image: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(image, (0, 0), self.cfg.blur_sigma) if self._blur[i] else image

    def _faded(self, i: int, image: np.ndarray) -> np.ndarray:
        """``SyntheticConfig.fades``: the contrast around the image's mean grey scaled by fade_contrast."""
        if not self._fade[i]:
            return image
        img = image.astype(np.float32)
        mean = np.float32(img.mean())
        return np.clip(np.round(mean + np.float32(self.cfg.fade_contrast) * (img - mean)), 0, 255).astype(np.uint8)

    def _sensor(self, i: int, cam: int, image: np.ndarray) -> np.ndarray:
        """Exposure and read noise (``SyntheticConfig.exposure`` / ``image_noise``); the same frame and camera
        always get the same noise, whatever order frames are rendered in."""
        cfg = self.cfg
        if cfg.exposure == 1.0 and cfg.image_noise == 0.0:
            return image
        out = image.astype(np.float32) * np.float32(cfg.exposure)
        if cfg.image_noise > 0:
            rng = np.random.default_rng([cfg.seed, 5, i, cam])  # stream 5: sensor noise
            out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(cfg.image_noise)
        return np.clip(np.round(out), 0, 255).astype(np.uint8)

    def lighting(self, i: int) -> tuple[float, float]:
        """(gain, gamma) applied to frame i: out = 255 * gain * (in / 255) ** gamma; (1, 1) without lighting_change."""
        if not self.cfg.lighting_change:
            return 1.0, 1.0
        p1, ph1, p2, ph2 = self._light
        tau = float(self._tau[i])
        return 1.0 + 0.35 * np.sin(2 * np.pi * tau / p1 + ph1), 1.0 + 0.3 * np.sin(2 * np.pi * tau / p2 + ph2)

    def _lighting_lut(self, i: int) -> np.ndarray | None:
        if not self.cfg.lighting_change:
            return None
        gain, gamma = self.lighting(i)
        x = np.arange(256) / 255.0
        return np.clip(np.round(255.0 * gain * x**gamma), 0, 255).astype(np.uint8)
