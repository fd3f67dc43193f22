"""The inertial side of the SLAM tracker: IMU buffer, initialisation, IMU pose prediction, VI local BA.

``SlamTracker`` owns one ``Vio`` when ``slam.inertial.enabled`` and calls it at four points: every frame
(``add_imu``, ``predict``, ``update``), after a keyframe is mapped (``after_keyframe``), and from local
mapping (``chain`` / ``solve``, which replace the visual-only BA once initialised).

Initialisation (ORB-SLAM3 / VINS vocabulary):

* static -- when the first ``imu.static_window_s`` seconds of IMU are still (EuRoC's pre-takeoff window):
  roll/pitch from the mean specific force, gyro bias from the mean rate, velocities zero;
* dynamic -- otherwise, once ``align_keyframes`` keyframes span ``align_min_span_s``: visual-inertial
  alignment of the up-to-scale keyframe poses with the IMU (gravity direction, velocities, gyro bias and,
  monocular, the metric scale), then one full VI BA over all keyframes.

Either way the world stays the map's frame (the first keyframe's camera) and the estimated gravity vector is
written, in that frame, into the preintegration parameters (``n_gravity``); rotating the map into a z-up world
instead would make the trajectory written before and after initialisation live in two frames. Monocular, the
map is scaled to metres once. Before initialisation the tracker runs exactly as vision-only.

Prediction: once initialised, a frame's pose prior is the IMU propagation of the previous frame's state
(pose from vision, velocity and bias propagated from the last keyframe's optimised state), replacing the
constant-velocity model. A frame vision cannot track (blackout, too few inliers) keeps the predicted pose
and velocity, so the trajectory follows the IMU until tracking recovers around the predicted pose.

IMU data is checked before it is believed. Each sample passes the gate of ``vslam.inertial.gate``
(sensor range, Hampel spike test) or is left out, and counted; ``finish`` warns once with the count and the first
rejected file line. A frame whose interval the accepted samples do not cover (a hole over
``imu.max_gap_s``, samples ending before the images, all rejected) turns the inertial side off: no IMU prediction
(constant velocity instead) and no IMU factors, so tracking and local BA are visual-only, with one warning per
stretch. An IMU factor that the VI BA finds wildly inconsistent with vision (``ba.max_imu_chi2``) is dropped and
turns the inertial side off the same way. When good data is back, the next keyframe restarts the IMU chain
(velocity from the last two tracked frames, the last bias, loose priors); gravity and the map frame stay those
of the initialisation. ``imu_state`` says "used" or "off" per frame (``FrameEstimate.imu``).

Why the mono-inertial settings (alignment keyframes >= 0.3 s apart, a 2 deg initial parallax and a
20-keyframe IMU chain, preset synthetic_vio_mono): alignments solved on keyframes 0.1 s apart let their
position noise shrink the scale (``vi_align(min_dt_s=)``), and a small two-view start read its rotation
error as gyro bias. The price is local BA time per keyframe (the IMU chain adds keyframes to the window).
Measurements: docs/inertial.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from vslam.backend.ba import BackendConfig, BAProblem, BAResult, StereoCamera, local_bundle_adjustment
from vslam.backend.inertial import (ImuChain, InertialBAConfig, initial_bias_covariance, prior_covariances,
                                    visual_inertial_bundle_adjustment)
from vslam.data.types import Calibration, Frame, SensorKind
from vslam.errors import ConfigError, InertialError
from vslam.geometry.se3 import inv_T, make_T
from vslam.inertial.buffer import ImuBuffer
from vslam.inertial.config import InertialConfig
from vslam.inertial.health import ImuHealth

if TYPE_CHECKING:
    from vslam.mapping.map import Map

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VioConfig:
    """``slam.inertial``: visual-inertial mode (off by default: vision-only behaviour unchanged).

    imu: IMU noise / gravity / static-init settings (``vslam.inertial.InertialConfig``).
    ba: the VI local BA (IMU chain length, treatment of the oldest state).
    init: "auto" = static when the sequence starts still, else dynamic alignment.
    align_keyframes / align_min_span_s: dynamic init waits for this many keyframes spanning this long.
    max_scale_change: stereo / RGB-D alignment scale outside [1/x, x] means a bad alignment (retry later).
    """

    enabled: bool = False
    imu: InertialConfig = field(default_factory=InertialConfig)
    ba: InertialBAConfig = field(default_factory=InertialBAConfig)
    init: Literal["auto", "static", "dynamic"] = "auto"
    align_keyframes: int = 6
    align_min_span_s: float = 1.5
    max_scale_change: float = 1.5
    # ORB-SLAM3's inertial rule: a keyframe at least every 0.5 s, so that IMU factors stay short (their
    # covariance grows with time) and dynamic initialisation gets its keyframes early.
    kf_max_interval_s: float = 0.5
    # ORB-SLAM3 refines its inertial initialisation twice (5 s and 15 s after it); here the alignment is re-run on
    # the VI-optimised keyframes of the last refine_window_s seconds at these times after a dynamic init: gravity,
    # velocities, gyro bias and (monocular) scale, which a windowed BA cannot move once keyframes are held.
    refine_after_s: tuple[float, ...] = (2.0, 5.0)
    refine_window_s: float = 4.0
    # the alignments solve on keyframes at least this far apart (``vi_align(min_dt_s=)``: visual position noise
    # shrinks the scale when keyframes are close)
    align_min_dt_s: float = 0.3
    # velocity prior sigma (m/s) of the keyframe that restarts the IMU chain after a stretch without usable IMU
    # data: its velocity is the mean over the last frame interval (``Vio._restart_chain``), off by up to
    # |acceleration| x frame interval / 2 (0.15 m/s for 3 m/s^2 at 10 Hz)
    restart_velocity_sigma: float = 0.2


@dataclass
class NavState:
    """Body state at IMU-clock time t: T_world_body (4,4), v (3,) world m/s, bias (6,) accel then gyro."""

    t: float
    T_world_body: np.ndarray
    v: np.ndarray
    bias: np.ndarray


class Vio:
    """Inertial state of one SLAM run (see module docstring)."""

    def __init__(self, calibration: Calibration, sensor: SensorKind, cfg: VioConfig, slam_map: Map):
        from vslam.inertial.preintegration import make_params

        self.cfg, self.sensor, self.map = cfg, sensor, slam_map
        if calibration.imu is None:  # a user mistake (e.g. inertial on a TUM or KITTI sequence): one line, no traceback
            raise ConfigError("slam.inertial.enabled is set, but the sequence has no IMU (EuRoC/TUM-VI imu0/ or synthetic)")
        self.noise = cfg.imu.noise(calibration.imu)
        self.params = make_params(self.noise, cfg.imu.gravity, None, cfg.imu.integration_sigma)
        self.T_bc = np.asarray(calibration.T_body_cam0, dtype=np.float64)
        self.T_cb = inv_T(self.T_bc)
        # Monocular, the map's scale itself comes from the IMU: vision cannot arbitrate the IMU factors' consistency
        self._ba_cfg = replace(cfg.ba, max_imu_chi2=float("inf")) if sensor == "mono" else cfg.ba
        self.buf = ImuBuffer(cfg.imu)
        self.health = ImuHealth(self.buf, cfg.imu.max_gap_s)
        self.imu_state = ""  # of the last frame: "used" / "off" (FrameEstimate.imu)
        self._chain_from = -np.inf  # IMU chains (and alignments) use keyframes from this IMU time on
        self._restart = False  # good IMU data back after a stretch off: the next keyframe restarts the chain
        self._restart_kf: int | None = None
        self._last_bias: np.ndarray | None = None
        self._tracked: list[tuple[float, np.ndarray]] = []  # (t, T_world_body) of the last two tracked frames
        self.ready = False
        self.method = ""  # "static" / "dynamic" once initialised
        self.nav: NavState | None = None
        self._pred: NavState | None = None
        self.marginals: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._t_first: float | None = None
        self._static_failed = cfg.init == "dynamic"
        self.scale = 1.0  # map scale applied at initialisation (monocular)
        self._align_tried = 0
        self._refined = 0  # refinements done (refine_after_s)
        self.full_chain = False  # True: the next BA links every keyframe (after an (re-)alignment, ORB-SLAM3's VI BA)
        self._t_init = 0.0

    def tc(self, t_cam: float) -> float:
        return self.cfg.imu.imu_time(t_cam)

    # -- per frame ------------------------------------------------------------
    def add_imu(self, frame: Frame) -> None:
        """Take the frame's IMU samples (gated) and whether they cover its interval (``vslam.inertial.health``):
        ``imu_state`` "used", or "off" over a stretch of missing or rejected samples and until the chain restarts."""
        self.buf.add(frame.imu)
        t = self.tc(frame.timestamp)
        if self._t_first is None:
            self._t_first = t
        change = self.health.frame(t)
        if change == "off":  # no IMU prediction, no IMU factors until the data is back
            self._chain_off(restart=False)
            if not self.ready and not self._static_failed:
                log.info("static IMU initialisation impossible: its window has a hole")
                self._static_failed = True
        elif change == "on":  # initialised: the next keyframe restarts the chain; else initialisation starts over
            self._chain_from, self._restart = t, self.ready
        if self.health.off:  # nothing to chain: keep only what the gate needs for context
            self.buf.trim(t - 1.0)
        gave_up = not self.ready and self._static_failed and self.cfg.init == "static"
        self.imu_state = "off" if self.health.off or self._restart or gave_up else "used"

    def finish(self) -> None:
        """End of the run: the gate's and the IMU stream's warnings (``ImuHealth.finish``)."""
        self.health.finish()

    def predict(self, t_cam: float) -> np.ndarray | None:
        """IMU-propagated T_world_cam (4,4) at camera time ``t_cam``, None before initialisation."""
        from vslam.inertial.preintegration import make_bias, predict, preintegrate

        if not self.ready or self.nav is None:
            return None
        t = self.tc(t_cam)
        if t <= self.nav.t:
            self._pred = NavState(t, self.nav.T_world_body.copy(), self.nav.v.copy(), self.nav.bias.copy())
        else:
            bias = make_bias(self.nav.bias[:3], self.nav.bias[3:])
            try:
                pim = preintegrate(self.buf.upto(t), self.nav.t, t, self.params, bias, self.cfg.imu.max_gap_s)
            except InertialError as e:  # a hole in the IMU stream: no inertial prediction for this frame
                log.warning("no IMU prediction at t=%.3f: %s", t, e)
                self._pred = None
                return None
            R, p, v = predict((self.nav.T_world_body[:3, :3], self.nav.T_world_body[:3, 3], self.nav.v), bias, pim)
            self._pred = NavState(t, make_T(R, p), v, self.nav.bias.copy())
        return self._pred.T_world_body @ self.T_bc

    def update(self, t_cam: float, T_world_cam: np.ndarray, tracked: bool) -> None:
        """The frame's final pose: vision's when tracked, else the prediction (kept as the state)."""
        t = self.tc(t_cam)
        self._tracked = (self._tracked + [(t, T_world_cam @ self.T_cb)])[-2:] if tracked else []
        if not self.ready or self._pred is None:
            return
        T_wb = T_world_cam @ self.T_cb if tracked else self._pred.T_world_body
        self.nav = NavState(self._pred.t, T_wb, self._pred.v, self._pred.bias)
        self._pred = None

    # -- keyframes ------------------------------------------------------------
    def wants_keyframe(self, t_cam: float) -> bool:
        """True when the newest keyframe is older than ``kf_max_interval_s``."""
        if not self.map.keyframes:
            return False
        return t_cam - self.map.keyframes[max(self.map.keyframes)].timestamp >= self.cfg.kf_max_interval_s

    def new_keyframe(self, kf_id: int) -> None:
        """Give a fresh keyframe the current inertial state as its initial guess (before local BA)."""
        if not self.ready or self.health.off:
            return
        kf = self.map.keyframes[kf_id]
        if self._restart:
            self._restart_chain(kf)
        elif self.nav is not None:
            kf.velocity, kf.bias = self.nav.v.copy(), self.nav.bias.copy()

    @property
    def predicting(self) -> bool:
        """The IMU propagated the state to the frame being tracked (``predict`` gave a pose)."""
        return self._pred is not None

    def new_map(self) -> None:
        """Tracking starts a new map (``vslam.tracking.atlas``) in the same gravity-aligned world frame: the IMU
        chain restarts at its first keyframes (velocity from vision, bias the last estimated), as after a stretch
        without IMU data; an initialisation not yet done starts over on the new map's keyframes."""
        self.marginals = {}
        if self.ready:
            self._chain_off(restart=True)
        else:
            self._t_first, self._align_tried = None, 0

    def _chain_off(self, restart: bool) -> None:
        """No IMU prediction and no IMU factors from now on; ``restart``: the next keyframe starts a new chain (else
        it waits for good data, ``add_imu``)."""
        self._chain_from, self._restart, self.nav, self._pred = np.inf, restart, None, None

    def _restart_chain(self, kf) -> None:
        """The first keyframe after a stretch without usable IMU data (or after a dropped IMU factor) starts a new
        IMU chain: velocity from the two last tracked frames (vision alone: the IMU around the restart may be what
        was bad), bias the last one estimated; both under loose priors in the chain's first VI BA
        (``restart_velocity_sigma``, the initial bias sigmas), where the IMU factor soon dominates them."""
        if len(self._tracked) < 2 or self._last_bias is None:
            return  # the next keyframe will
        (t0, T0), (t1, T1) = self._tracked
        kf.velocity = (T1[:3, 3] - T0[:3, 3]) / (t1 - t0)
        kf.bias = self._last_bias.copy()
        self._restart, self._restart_kf = False, kf.id
        self._chain_from = self.tc(kf.timestamp)
        log.info("IMU chain restarted at keyframe %d (t=%.3f s), velocity %s m/s", kf.id, self._chain_from,
                 np.round(kf.velocity, 3))

    def after_keyframe(self, kf_id: int) -> None:
        """Local BA has run: restart propagation from the keyframe's optimised state; trim the buffer."""
        if not self.ready:
            return
        kf = self.map.keyframes[kf_id]
        if kf.velocity is None or kf.bias is None or self.tc(kf.timestamp) < self._chain_from:
            return
        self.nav = NavState(self.tc(kf.timestamp), kf.T_world_cam @ self.T_cb, kf.velocity.copy(), kf.bias.copy())
        self._last_bias = kf.bias.copy()
        ids = self.chain()
        if ids:  # keep what the IMU chain and a later refinement need
            keep = self.tc(self.map.keyframes[ids[0]].timestamp)
            if self.method == "dynamic" and self._refined < len(self.cfg.refine_after_s):
                keep = min(keep, self.nav.t - self.cfg.refine_window_s)
            self.buf.trim(keep - 0.1)

    def chain(self) -> list[int]:
        """Ids of the IMU chain: the newest ``ba.chain`` keyframes (all with ``full_chain``) that have an inertial
        state and IMU samples still in the buffer, in time order."""
        if not self.ready or len(self.buf.t) == 0:
            return []
        t0 = max(float(self.buf.t[0]), self._chain_from)
        ids = sorted(k for k, kf in self.map.keyframes.items() if kf.velocity is not None and self.tc(kf.timestamp) >= t0)
        return ids if self.full_chain else ids[-self.cfg.ba.chain:]

    # -- local BA ---------------------------------------------------------------
    def solve(self, problem: BAProblem, camera: StereoCamera, backend: BackendConfig) -> BAResult:
        """VI local BA over ``problem`` + the IMU chain; writes velocity / bias into the chain's keyframes."""
        ids = [k for k in self.chain() if k in problem.poses]
        kfs = [self.map.keyframes[k] for k in ids]
        stamps = np.array([self.tc(kf.timestamp) for kf in kfs])
        cov_v, cov_b = prior_covariances(self.marginals.get(ids[0]), self.cfg.ba)
        if ids[0] not in self.marginals:  # never optimised as a middle state: the initialisation (or restart) prior
            sigma_v = self.cfg.restart_velocity_sigma if ids[0] == self._restart_kf else self.cfg.imu.prior_velocity_sigma
            cov_v = np.eye(3) * sigma_v**2
            cov_b = initial_bias_covariance(self.cfg.imu.prior_accel_bias_sigma, self.cfg.imu.prior_gyro_bias_sigma)
        chain = ImuChain(np.array(ids), stamps, np.array([kf.velocity for kf in kfs]), np.array([kf.bias for kf in kfs]),
                         self.buf.upto(float(stamps[-1])), self.params, self.T_bc, cov_v, cov_b, self.cfg.imu.max_gap_s)
        try:
            res = visual_inertial_bundle_adjustment(problem, chain, camera, backend, self._ba_cfg,
                                                    marginal_for=ids[1] if len(ids) > 1 else None)
        except InertialError as e:  # the per-frame coverage test should have turned the chain off before this
            log.warning("VI BA impossible (%s); visual-only BA, the IMU chain restarts at the next keyframe", e)
            self._chain_off(restart=True)
            return local_bundle_adjustment(problem, camera, backend)
        log.debug("IMU factor chi2 %s", {k: round(v, 1) for k, v in res.imu_chi2.items()})
        for i, j, chi2 in res.dropped:  # the stretch is off: the chain starts again at the next keyframe
            log.warning("IMU factor between keyframes %d and %d (t=%.3f to %.3f s) disagrees with vision (chi2 %.0f > "
                        "%.0f): dropped; no IMU prediction or factors until the chain restarts at the next keyframe",
                        i, j, self.tc(self.map.keyframes[i].timestamp), self.tc(self.map.keyframes[j].timestamp), chi2,
                        self.cfg.ba.max_imu_chi2)
        if res.dropped:
            self._chain_off(restart=True)
        for k in ids:
            self.map.keyframes[k].velocity = res.velocity[k]
            self.map.keyframes[k].bias = res.bias[k]
        self.marginals.update(res.marginal)
        for k in [k for k in self.marginals if k < ids[0]]:
            del self.marginals[k]
        return res.ba

    # -- initialisation -----------------------------------------------------------
    def try_initialize(self) -> tuple[np.ndarray, float] | None:
        """Run static or dynamic initialisation when its data is there.

        -> (T_new_old (4,4) transform of the world (identity: see module docstring), scale) applied to the
        map, or None (not yet).
        The caller moves its own pose state with ``transform_pose``.
        """
        if self.ready:
            return self._try_refine()
        if self._t_first is None or len(self.map.keyframes) == 0:
            return None
        if not self._static_failed:
            out = self._try_static()
            if out is not None:
                return out
        if self._static_failed and self.cfg.init != "static":
            return self._try_dynamic()
        return None

    def _try_static(self) -> tuple[np.ndarray, float] | None:
        from vslam.inertial.init import static_init

        c = self.cfg.imu
        if self._t_first is None or len(self.buf.t) < 2:  # no IMU samples yet
            return None
        t0 = self._t_first
        t1 = min(float(self.buf.t[-1]), t0 + c.static_window_s)
        if t1 - t0 < min(0.5, c.static_window_s):  # a motion test needs a few hundred ms
            return None
        try:
            st = static_init(self.buf.samples(), t0, t1, c.gravity,
                             c.still_accel_std, c.still_gyro_std, smooth_s=c.still_smooth_s,
                             max_force_error=c.still_max_force_error)
        except InertialError as e:
            log.info("static initialisation impossible (%s)", e)
            self._static_failed = True
            return None
        if st.still and t1 < t0 + c.static_window_s:
            return None  # still so far: wait for the whole window
        if not st.still:
            if self.cfg.init == "static":  # no fallback asked for: the run stays vision-only
                log.warning("static initialisation rejected (%s); inertial mode stays off", st.reason)
            self._static_failed = True
            return None
        # The body is still: world "up" in the body frame is the mean specific force direction.
        kf0 = self.map.keyframes[min(self.map.keyframes)]
        R_map_body = (kf0.T_world_cam @ self.T_cb)[:3, :3]
        gravity = -c.gravity * (R_map_body @ st.up_body)
        bias = np.concatenate([np.zeros(3), st.gyro_bias])
        T = np.eye(4)
        self._finish_init(T, 1.0, gravity, {k: np.zeros(3) for k in self.map.keyframes}, bias, "static")
        log.info("static IMU initialisation: gyro bias %s rad/s, |f|-g %.3f m/s^2", np.round(st.gyro_bias, 5),
                 st.force_norm_error)
        return T, 1.0

    def _try_dynamic(self) -> tuple[np.ndarray, float] | None:
        from vslam.inertial.init import vi_align

        kfs = sorted((k for k in self.map.keyframes.values() if self.tc(k.timestamp) >= self._chain_from),
                     key=lambda k: k.timestamp)
        if not kfs or len(kfs) < self.cfg.align_keyframes or kfs[-1].timestamp - kfs[0].timestamp < self.cfg.align_min_span_s:
            return None
        if len(kfs) == self._align_tried:  # same keyframes as the last failed try: same answer
            return None
        self._align_tried = len(kfs)
        stamps = np.array([self.tc(k.timestamp) for k in kfs])
        T_map_cam = np.array([k.T_world_cam for k in kfs])
        try:
            al = vi_align(stamps, T_map_cam, self.T_bc, imu=self.buf.upto(float(stamps[-1])), params=self.params,
                          gravity=self.cfg.imu.gravity, min_dt_s=self.cfg.align_min_dt_s)
        except InertialError as e:
            log.info("visual-inertial alignment failed (%s); retrying at the next keyframe", e)
            return None
        scale = float(al.scale) if self.sensor == "mono" else 1.0
        if self.sensor != "mono" and not (1 / self.cfg.max_scale_change < al.scale < self.cfg.max_scale_change):
            log.info("visual-inertial alignment scale %.3f on a metric map: rejected, retrying", al.scale)
            return None
        T = np.eye(4)
        # map frame; velocities are in the aligned (scale x map) units, so metric maps take them / al.scale
        vel = {k.id: al.R_world_visual.T @ al.velocities[i] * (scale / al.scale) for i, k in enumerate(kfs)}
        bias = np.concatenate([np.zeros(3), al.gyro_bias])
        self._finish_init(T, scale, np.asarray(al.gravity_visual, dtype=np.float64), vel, bias, "dynamic")
        log.info("visual-inertial alignment over %d keyframes: scale %.4f, gyro bias %s", len(kfs), al.scale,
                 np.round(al.gyro_bias, 5))
        return T, scale

    def _try_refine(self) -> tuple[np.ndarray, float] | None:
        if self.method != "dynamic" or self._refined >= len(self.cfg.refine_after_s) or self.nav is None:
            return None
        if self.nav.t - self._t_init < self.cfg.refine_after_s[self._refined]:
            return None
        from vslam.inertial.init import vi_align

        self._refined += 1
        t_end = self.tc(self.map.keyframes[max(self.map.keyframes)].timestamp)
        kfs = [k for k in sorted(self.map.keyframes.values(), key=lambda k: k.timestamp)
               if k.velocity is not None and self.tc(k.timestamp) >= t_end - self.cfg.refine_window_s
               and self.tc(k.timestamp) >= max(self.buf.t[0], self._chain_from)]
        if len(kfs) < self.cfg.align_keyframes:
            return None
        stamps = np.array([self.tc(k.timestamp) for k in kfs])
        b = kfs[-1].bias
        try:
            al = vi_align(stamps, np.array([k.T_world_cam for k in kfs]), self.T_bc, imu=self.buf.upto(float(stamps[-1])),
                          params=self.params, gyro_bias=b[3:], gravity=self.cfg.imu.gravity,
                          min_dt_s=self.cfg.align_min_dt_s)
        except InertialError as e:
            log.info("inertial refinement failed (%s)", e)
            return None
        scale = float(al.scale) if self.sensor == "mono" else 1.0
        if not (1 / self.cfg.max_scale_change < al.scale < self.cfg.max_scale_change):
            log.info("inertial refinement scale %.3f: rejected", al.scale)
            return None
        transform_map(self.map, np.eye(4), scale)  # also rescales every stored velocity
        self.params.n_gravity = np.asarray(al.gravity_visual, dtype=np.float64)
        for i, k in enumerate(kfs):
            k.velocity = al.R_world_visual.T @ al.velocities[i] * (scale / al.scale)
        self.scale *= scale
        last = self.map.keyframes[max(self.map.keyframes)]
        self.nav = NavState(self.tc(last.timestamp), last.T_world_cam @ self.T_cb, last.velocity.copy(), last.bias.copy())
        log.info("inertial refinement %d over %d keyframes: scale %.4f", self._refined, len(kfs), al.scale)
        return np.eye(4), scale

    def _finish_init(self, T: np.ndarray, scale: float, gravity: np.ndarray, velocity: dict[int, np.ndarray],
                     bias: np.ndarray, method: str) -> None:
        """Apply an initialisation: map transform (T, scale), gravity (3,) m/s^2 in the map frame, states."""
        transform_map(self.map, T, scale)
        self.params.n_gravity = T[:3, :3] @ gravity
        self.gravity = self.params.n_gravity
        for k, v in velocity.items():  # (keyframes before a stretch without IMU data have none)
            kf = self.map.keyframes[k]
            kf.velocity = np.asarray(v, dtype=np.float64).copy()
            kf.bias = bias.copy()
        self.ready, self.method, self.scale = True, method, scale
        self._last_bias = bias.copy()
        self._t_init = self.tc(self.map.keyframes[max(self.map.keyframes)].timestamp)
        last = self.map.keyframes[max(self.map.keyframes)]
        self.nav = NavState(self.tc(last.timestamp), last.T_world_cam @ self.T_cb, last.velocity.copy(), bias.copy())

    def transform_pose(self, T_world_cam: np.ndarray, T: np.ndarray, scale: float) -> np.ndarray:
        """A T_world_cam of the old world in the new one (x' = T (scale x))."""
        out = np.array(T_world_cam, dtype=np.float64)
        out[:3, 3] *= scale
        return T @ out


def transform_map(slam_map: Map, T: np.ndarray, scale: float) -> None:
    """Move the whole map into a new world: x_new = R (scale x_old) + t with T = (R, t); velocities rotate."""
    R, t = T[:3, :3], T[:3, 3]
    for kf in slam_map.keyframes.values():
        P = kf.T_world_cam.copy()
        P[:3, 3] *= scale
        kf.T_world_cam = T @ P
        if kf.velocity is not None:
            kf.velocity = scale * (R @ kf.velocity)
        if scale != 1.0:
            kf.depth = kf.depth * scale
    for mp in slam_map.points.values():
        mp.xyz = R @ (scale * mp.xyz) + t
    slam_map.touch()
