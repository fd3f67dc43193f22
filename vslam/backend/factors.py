"""GTSAM factor construction for visual BA. GTSAM types are made and consumed here and in ``ba.py`` only.

Keys: ``X(kf_id)`` for a keyframe pose (gtsam.Pose3 = T_world_cam), ``L(point_id)`` for a landmark
(gtsam.Point3 in world, metres). GTSAM's projection factors take the *camera pose in the world*:
``GenericProjectionFactorCal3_S2`` and ``GenericStereoFactor3D`` project with
``PinholeCamera(pose).project(p) = K * pose.transformTo(p)`` = K * T_cam_world * p.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

__all__ = ["L", "X", "FactorBuilder", "pose3", "pose_matrix", "lm_params"]

#: Fixed keyframes are held by a PriorFactorPose3 of this sigma (rad / m); None -> NonlinearEqualityPose3.
#: Measured (``python -m tests.backend.bench_ba``, same results either way): NonlinearEquality linearises to
#: a *constrained* noise model, which slows elimination wherever the fixed pose shares a clique with many
#: others -- 6 kf x 200 pts, every point in every keyframe: 185-205 ms vs 59-61 ms per BA call (one linear
#: solve 16 vs 2.5 ms); 10-kf windows: 220-275 ms vs 165-255 ms. 1e-6 moves a fixed pose by < 1e-9 and keeps
#: the Hessian well inside double precision (visual blocks ~1e4-1e6, prior 1e12). The caller never sees
#: the held pose: BAResult leaves fixed keyframes out.
FIXED_WITH_PRIOR_SIGMA: float | None = 1e-6


class FactorBuilder:
    """Makes one robust visual factor per observation; calibrations and noise models are built once.

    camera: ``StereoCamera`` (pixels, baseline in metres); huber_k: Huber threshold in sigmas.
    Noise models are cached per (dimension, sigma), so per-observation sigmas (pyramid levels) stay cheap.
    """

    def __init__(self, camera, huber_k: float, T_body_cam: np.ndarray | None = None):
        # T_body_cam (4,4): poses X(k) are then T_world_body and the camera sits at body_P_sensor (VI BA)
        self._bPs = None if T_body_cam is None else pose3(T_body_cam)
        self.K_mono = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        b = max(camera.baseline, 1e-12)  # unused when baseline == 0 (every factor is then mono)
        self.K_stereo = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, b)
        self._huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k)
        self._disparity_sigma = float(camera.disparity_sigma)
        self._models: dict[tuple[int, float], gtsam.noiseModel.Base] = {}

    def noise(self, dim: int, sigma: float) -> gtsam.noiseModel.Base:
        """Huber-robust model of ``dim`` (2 mono, 3 stereo) and ``sigma`` pixels, built once: isotropic, or for
        stereo with a disparity sigma (RGB-D, see ``StereoCamera``) the covariance of (uL, uR = uL - d, v)."""
        key = (dim, float(sigma))
        model = self._models.get(key)
        if model is None:
            s2 = float(sigma) ** 2
            if dim == 3 and self._disparity_sigma > 0:
                cov = np.array([[s2, s2, 0.0], [s2, s2 + self._disparity_sigma**2, 0.0], [0.0, 0.0, s2]])
                base = gtsam.noiseModel.Gaussian.Covariance(cov)
            else:
                base = gtsam.noiseModel.Isotropic.Sigma(dim, float(sigma))
            model = gtsam.noiseModel.Robust.Create(self._huber, base)
            self._models[key] = model
        return model

    def hold(self, key: int, T: np.ndarray) -> gtsam.NonlinearFactor:
        """Factor holding pose ``key`` at T (4,4) T_world_cam: tight prior, or NonlinearEquality (see above)."""
        if FIXED_WITH_PRIOR_SIGMA is None:
            return gtsam.NonlinearEqualityPose3(key, pose3(T))
        model = self._models.get((6, FIXED_WITH_PRIOR_SIGMA))
        if model is None:
            model = self._models[(6, FIXED_WITH_PRIOR_SIGMA)] = gtsam.noiseModel.Isotropic.Sigma(6, FIXED_WITH_PRIOR_SIGMA)
        return gtsam.PriorFactorPose3(key, pose3(T), model)

    def between(self, a: int, b: int, T_a_b: np.ndarray, cov: np.ndarray) -> gtsam.NonlinearFactor:
        """Robust relative-pose factor X(a)^-1 X(b) = T_a_b of covariance ``cov`` (6,6: rotation, translation of
        the right perturbation; a wrong measurement is then bounded like a wrong observation)."""
        base = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, np.float64))
        model = gtsam.noiseModel.Robust.Create(self._huber, base)
        return gtsam.BetweenFactorPose3(X(a), X(b), pose3(T_a_b), model)

    def factors(
        self, kf: np.ndarray, pt: np.ndarray, meas: np.ndarray, stereo: np.ndarray, sigma: np.ndarray
    ) -> list[gtsam.NonlinearFactor]:
        """One factor per row: kf, pt (N,) int ids; meas (N,3) (uL, v, uR); stereo (N,) bool; sigma (N,) px."""
        if self._bPs is not None:
            return self._factors_body(kf, pt, meas, stereo, sigma)
        out = []
        Ks, Km = self.K_stereo, self.K_mono
        for k, j, (u, v, r), st, s in zip(kf.tolist(), pt.tolist(), meas.tolist(), stereo.tolist(), sigma.tolist()):
            if st:
                out.append(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, r, v), self.noise(3, s), X(k), L(j), Ks))
            else:
                out.append(gtsam.GenericProjectionFactorCal3_S2(np.array([u, v]), self.noise(2, s), X(k), L(j), Km))
        return out

    def _factors_body(self, kf, pt, meas, stereo, sigma) -> list[gtsam.NonlinearFactor]:
        """As ``factors`` with the camera at ``body_P_sensor`` of body poses X(k)."""
        out = []
        bPs, Ks, Km = self._bPs, self.K_stereo, self.K_mono
        for k, j, (u, v, r), st, s in zip(kf.tolist(), pt.tolist(), meas.tolist(), stereo.tolist(), sigma.tolist()):
            if st:
                out.append(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, r, v), self.noise(3, s), X(k), L(j), Ks, bPs))
            else:
                out.append(gtsam.GenericProjectionFactorCal3_S2(np.array([u, v]), self.noise(2, s), X(k), L(j), Km, bPs))
        return out


def pose3(T: np.ndarray) -> gtsam.Pose3:
    """(4,4) rigid transform -> gtsam.Pose3 (rotation re-orthonormalised by GTSAM's Rot3 constructor)."""
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


def pose_matrix(p: gtsam.Pose3) -> np.ndarray:
    """gtsam.Pose3 -> (4,4) float64."""
    return np.asarray(p.matrix(), dtype=np.float64)


def lm_params(max_iterations: int) -> gtsam.LevenbergMarquardtParams:
    """Silent LM with ``max_iterations``; stops early once the error stops falling (relative 1e-6).

    lambdaInitial = 1 (GTSAM default 1e-5) and Nielsen's adaptive lambda update (Ceres/g2o style) instead of
    a fixed x10 factor. Damping of 1 (whitened px^2 per m^2 or rad^2) is nothing next to a well-observed pose
    (~1e6) or point (~1e4) but stops a near-undetermined direction -- the depth of a mono point seen twice with
    little parallax -- from taking a huge first Gauss-Newton step behind a camera, where GTSAM's factors
    return a constant error with a zero Jacobian and the point is stuck for good. Measured on the 3000-obs
    window with 5 % outliers (``tests/backend/bench_ba.py`` setup, 3 seeds): default params end the first
    10 iterations at robust cost ~26 000 (points stuck behind cameras) and take ~355 ms for both rounds;
    these reach ~4 900 and take ~255 ms, with equal or smaller pose error.
    """
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(int(max_iterations))
    p.setRelativeErrorTol(1e-6)  # a relative decrease below 1e-6 moves nothing measurable
    p.setAbsoluteErrorTol(1e-10)
    p.setlambdaInitial(1.0)
    p.setUseFixedLambdaFactor(False)
    p.setVerbosityLM("SILENT")
    return p
