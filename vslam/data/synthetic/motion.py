"""Analytic body trajectory of the synthetic camera rig, with exact derivatives.

The body (IMU) frame is x forward, y left, z up; the world is z up with
gravity (0, 0, -9.81). The body moves along a base path (an ellipse in the
horizontal plane, or a straight line down the street) plus small sums of
sines on x, y, z, yaw, pitch and roll. Every term has closed-form first and
second derivatives, so velocities, accelerations and angular rates are exact
and an IMU built from them integrates back to the ground truth up to the
integration scheme's own error.

Time inside this module is ``tau``: seconds since frame 0.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from vslam.data.synthetic.config import CAMERA_HEIGHT, ROOM_HI, ROOM_LO, SyntheticConfig
from vslam.geometry.se3 import make_T, so3_exp

logger = logging.getLogger(__name__)

GRAVITY = np.array([0.0, 0.0, -9.81])  # world frame, m/s^2

# Laps of the closed path in a sequence: > 1 so the path revisits its start
# with loop=True, < 1 so it never comes back without.
LOOP_LAPS = 1.3
OPEN_LAPS = 0.6

# Camera (z forward, x right, y down) -> body (x forward, y left, z up), then a
# small fixed misalignment so code that assumes a pure axis permutation fails.
_R_BODY_CAM_NOMINAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BODY_CAM0 = make_T(_R_BODY_CAM_NOMINAL @ so3_exp(np.array([0.01, -0.02, 0.015])), np.array([0.06, 0.015, -0.02]))


@dataclass(frozen=True)
class Channel:
    """One smooth scalar signal: c0 + c1*tau + sum_i amp_i * sin(freq_i * tau + phase_i).

    freq in rad/s. ``eval`` returns the value and its first two derivatives.
    """

    c0: float = 0.0
    c1: float = 0.0
    amp: tuple[float, ...] = ()
    freq: tuple[float, ...] = ()
    phase: tuple[float, ...] = ()

    def eval(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        tau = np.asarray(tau, dtype=np.float64)
        v = self.c0 + self.c1 * tau
        d1 = np.full_like(tau, self.c1)
        d2 = np.zeros_like(tau)
        for a, w, p in zip(self.amp, self.freq, self.phase):
            arg = w * tau + p
            s, c = np.sin(arg), np.cos(arg)
            v = v + a * s
            d1 = d1 + a * w * c
            d2 = d2 - a * w * w * s
        return v, d1, d2


@dataclass(frozen=True)
class BasePath:
    """Ellipse x = cx + a cos(th), y = cy + b sin(th), th = omega*tau + theta0 (counter-clockwise),
    or, with a = b = 0, the line x = cx + line_speed * tau, y = cy.

    ``eval`` gives xy position, velocity, acceleration and the heading (direction
    of travel, radians about world z) with its first two derivatives.
    """

    cx: float
    cy: float
    a: float = 0.0
    b: float = 0.0
    omega: float = 0.0
    theta0: float = 0.0
    line_speed: float = 0.0

    @property
    def is_loop(self) -> bool:
        return self.a > 0

    def eval(self, tau: np.ndarray) -> tuple[np.ndarray, ...]:
        tau = np.asarray(tau, dtype=np.float64)
        if not self.is_loop:
            z = np.zeros_like(tau)
            pos = np.stack([self.cx + self.line_speed * tau, z + self.cy], axis=-1)
            vel = np.stack([z + self.line_speed, z], axis=-1)
            return pos, vel, np.zeros_like(pos), z, z, z
        th = self.omega * tau + self.theta0
        s, c = np.sin(th), np.cos(th)
        a, b, w = self.a, self.b, self.omega
        pos = np.stack([self.cx + a * c, self.cy + b * s], axis=-1)
        vel = np.stack([-a * w * s, b * w * c], axis=-1)
        acc = np.stack([-a * w * w * c, -b * w * w * s], axis=-1)
        heading = np.arctan2(b * c, -a * s)
        # d/dtau atan2(vy, vx) = (vx ay - vy ax) / |v|^2, which for the ellipse is w a b / D.
        D = a * a * s * s + b * b * c * c
        rate = w * a * b / D
        rate_dot = -w * a * b * (w * (a * a - b * b) * np.sin(2 * th)) / (D * D)
        return pos, vel, acc, heading, rate, rate_dot


@dataclass(frozen=True)
class BodyState:
    """Body state at N times: R_world_body (N,3,3), p/v/a world (N,3) m, m/s, m/s^2, omega_body (N,3) rad/s."""

    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    omega_body: np.ndarray

    @property
    def T_world_body(self) -> np.ndarray:
        T = np.tile(np.eye(4), (len(self.p), 1, 1))
        T[:, :3, :3] = self.R
        T[:, :3, 3] = self.p
        return T


def euler_zyx_to_R(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), vectorised: (N,) radians -> (N,3,3)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty((len(yaw), 3, 3))
    R[:, 0] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1)
    R[:, 1] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1)
    R[:, 2] = np.stack([-sp, cp * sr, cp * cr], axis=-1)
    return R


@dataclass(frozen=True)
class RigMotion:
    """Body trajectory = base path + wobble channels; yaw = heading + yaw_offset + yaw wobble."""

    path: BasePath
    x: Channel
    y: Channel
    z: Channel
    yaw: Channel
    pitch: Channel
    roll: Channel
    T_body_cam0: np.ndarray

    def body_state(self, tau: np.ndarray) -> BodyState:
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
        pos, vel, acc, heading, h1, h2 = self.path.eval(tau)
        xs, ys, zs = self.x.eval(tau), self.y.eval(tau), self.z.eval(tau)
        p = np.stack([pos[:, 0] + xs[0], pos[:, 1] + ys[0], zs[0]], axis=-1)
        v = np.stack([vel[:, 0] + xs[1], vel[:, 1] + ys[1], zs[1]], axis=-1)
        a = np.stack([acc[:, 0] + xs[2], acc[:, 1] + ys[2], zs[2]], axis=-1)
        yw, y1, _ = self.yaw.eval(tau)
        pt, p1, _ = self.pitch.eval(tau)
        rl, r1, _ = self.roll.eval(tau)
        psi, dpsi = heading + yw, h1 + y1
        # Body angular velocity of ZYX Euler angles: Rx^T Ry^T (0,0,psi') + Rx^T (0,theta',0) + (phi',0,0).
        omega = np.stack(
            [
                r1 - np.sin(pt) * dpsi,
                np.cos(rl) * p1 + np.sin(rl) * np.cos(pt) * dpsi,
                -np.sin(rl) * p1 + np.cos(rl) * np.cos(pt) * dpsi,
            ],
            axis=-1,
        )
        return BodyState(euler_zyx_to_R(psi, pt, rl), p, v, a, omega)

    def T_world_cam0(self, tau: np.ndarray) -> np.ndarray:
        """(N,4,4) ground-truth cam0 poses at ``tau`` (s since frame 0)."""
        return self.body_state(tau).T_world_body @ self.T_body_cam0


def _ellipse_perimeter(a: float, b: float) -> float:
    """Ramanujan's approximation (relative error < 1e-4 for a/b <= 3, plenty for choosing a size)."""
    return float(np.pi * (3 * (a + b) - np.sqrt((3 * a + b) * (a + 3 * b))))


def _wobble(rng: np.random.Generator, amp: float, acc_max: float, freqs: np.ndarray, c0: float = 0.0) -> Channel:
    """c0 plus two small sines; amplitude capped so amp * freq^2 <= acc_max keeps the motion hand-held, not violent."""
    f = rng.choice(freqs, size=2, replace=False)
    amps = [min(amp * rng.uniform(0.5, 1.0), acc_max / (w * w)) for w in f]
    return Channel(c0, 0.0, tuple(amps), tuple(float(w) for w in f), tuple(rng.uniform(0, 2 * np.pi, 2)))


def _loop_size(distance: float, laps: float, aspect: float, min_a: float, max_a: float) -> tuple[float, float, float]:
    """Semi-axes (a, b = a/aspect) so that ``laps`` laps cover ``distance``, with a clipped to
    [min_a, max_a]; returns them with the laps actually covered."""
    unit = _ellipse_perimeter(1.0, 1.0 / aspect)
    a = float(np.clip(distance / laps / unit, min_a, max_a))
    return a, a / aspect, distance / (a * unit)


def build_motion(cfg: SyntheticConfig) -> RigMotion:
    """The body trajectory of ``cfg``: seeded, smooth, analytic; see the module doc."""
    rng = np.random.default_rng([cfg.seed, 1])  # stream 1: motion (independent of textures and IMU noise)
    distance = cfg.mean_speed * cfg.duration
    if cfg.scene == "room":
        path = _room_path(cfg, rng, distance)
        # Look between forward and outward (outward = heading - 90 deg for counter-clockwise travel):
        # walls at 1.5-6 m and sideways parallax for monocular initialisation.
        yaw_offset = -0.5
    elif cfg.scene == "corridor":  # straight down the middle, within 15 cm of the axis
        path = BasePath(0.0, rng.uniform(-0.15, 0.15), line_speed=cfg.mean_speed)
        yaw_offset = 0.0
    else:
        path = _street_path(cfg, rng, distance)
        yaw_offset = 0.0
    return RigMotion(path, *_wobbles(rng, cfg, path, yaw_offset), T_body_cam0=T_BODY_CAM0)


def _room_path(cfg: SyntheticConfig, rng: np.random.Generator, distance: float) -> BasePath:
    """An ellipse around the room centre that keeps >= 1.4 m to every wall."""
    max_a = ROOM_HI[0] - 1.6
    aspect = max_a / (ROOM_HI[1] - 1.4)
    # An open path keeps the default sequence's size (about 8 m around) however short the
    # sequence, so short test sequences move like long ones; a loop must close in time.
    min_a = 0.0 if cfg.loop else 1.5
    a, b, laps = _loop_size(distance, LOOP_LAPS if cfg.loop else OPEN_LAPS, aspect, min_a, max_a)
    if not cfg.loop and laps > 0.75:
        logger.warning("synthetic: a %.1f m open path does not fit the room; it covers %.2f laps and comes back", distance, laps)
    cx, cy = 0.5 * (ROOM_LO[0] + ROOM_HI[0]), 0.5 * (ROOM_LO[1] + ROOM_HI[1])
    return BasePath(cx, cy, a, b, 2 * np.pi * laps / cfg.duration, rng.uniform(0, 2 * np.pi))


def _street_path(cfg: SyntheticConfig, rng: np.random.Generator, distance: float) -> BasePath:
    """Straight down the street (+x), or a loop in the lanes (|y| <= 2.5 m; sidewalks start at 4 m):
    a circle while it fits, then an ellipse elongated down the street."""
    if not cfg.loop:
        return BasePath(0.0, rng.uniform(-1.0, 1.0), line_speed=cfg.mean_speed)
    perimeter = distance / LOOP_LAPS
    a = b = min(perimeter / (2 * np.pi), 2.5)
    if perimeter > 2 * np.pi * 2.5:
        a = _solve_a(perimeter, b)
    laps = distance / _ellipse_perimeter(a, b)
    return BasePath(0.0, 0.0, a, b, 2 * np.pi * laps / cfg.duration, rng.uniform(0, 2 * np.pi))


def _solve_a(perimeter: float, b: float) -> float:
    """Semi-axis a >= b of the ellipse with semi-axis b and the given perimeter (bisection)."""
    lo, hi = b, perimeter
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _ellipse_perimeter(mid, b) < perimeter else (lo, mid)
    return 0.5 * (lo + hi)


def _wobbles(rng: np.random.Generator, cfg: SyntheticConfig, path: BasePath, yaw_offset: float) -> tuple[Channel, ...]:
    """x, y, z, yaw, pitch, roll channels. On a loop every frequency is a multiple of the lap
    rate, so the whole motion is periodic and a loop returns exactly to its start."""
    base = 2 * np.pi * np.array([0.3, 0.45, 0.7, 0.95, 1.2, 1.5])  # rad/s, hand-held band
    if path.is_loop:
        k = np.unique(np.maximum(1, np.round(base / path.omega)))
        base = (k if len(k) >= 4 else np.arange(1, 5)) * path.omega
    lane_drift = 0.6 if cfg.scene == "street" and not path.is_loop else 0.04  # slow lane changes
    return (
        _wobble(rng, 0.04, 1.0, base),  # x
        _wobble(rng, lane_drift, 1.0, base),  # y
        _wobble(rng, 0.03, 0.8, base, c0=CAMERA_HEIGHT + rng.uniform(-0.1, 0.1)),  # z
        _wobble(rng, 0.06, 1.5, base, c0=yaw_offset),  # yaw, added to the heading
        _wobble(rng, 0.04, 1.5, base, c0=-0.08),  # pitch: a little nose-down
        _wobble(rng, 0.03, 1.5, base),  # roll
    )
