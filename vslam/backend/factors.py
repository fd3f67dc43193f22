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

__all__ = ["L", "X", "FactorBuilder", "FactorCache", "symbol_keys", "pose3", "pose_matrix", "lm_params"]

#: Fixed keyframes are held by a PriorFactorPose3 of this sigma (rad / m); None -> NonlinearEqualityPose3.
#: Same results either way, but NonlinearEquality linearises to a *constrained* noise model, which slows
#: elimination wherever the fixed pose shares a clique with many others (``python -m tests.backend.bench_ba``;
#: docs/backend.md, "Fixed keyframes and LM damping"). 1e-6 moves a fixed pose by < 1e-9 and keeps
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
        out = []
        extra = () if self._bPs is None else (self._bPs,)  # body poses: the camera at body_P_sensor
        Ks, Km = (self.K_stereo, *extra), (self.K_mono, *extra)
        stereo_f, mono_f, sp2 = gtsam.GenericStereoFactor3D, gtsam.GenericProjectionFactorCal3_S2, gtsam.StereoPoint2
        uv = np.ascontiguousarray(meas[:, :2], dtype=np.float64)  # rows: the mono measurement, no array per factor
        rows = zip(symbol_keys("x", kf), symbol_keys("l", pt), meas.tolist(), uv, stereo.tolist(),
                   self._row_models(stereo, sigma))
        for xk, lk, (u, v, r), uv_i, st, model in rows:
            if st:
                out.append(stereo_f(sp2(u, r, v), model, xk, lk, *Ks))
            else:
                out.append(mono_f(uv_i, model, xk, lk, *Km))
        return out

    def _row_models(self, stereo: np.ndarray, sigma: np.ndarray) -> list[gtsam.noiseModel.Base]:
        """``noise(3 if stereo else 2, sigma)`` of each row, looked up once per distinct (stereo, sigma)."""
        if len(sigma) == 0:
            return []
        values, inverse = np.unique(np.asarray(sigma, np.float64), return_inverse=True)
        table = [self.noise(2, s) for s in values.tolist()] + [self.noise(3, s) for s in values.tolist()]
        code = inverse.reshape(-1) + values.size * np.asarray(stereo, bool)
        return [table[c] for c in code.tolist()]


class FactorCache:
    """The visual factors of the last window, for the next one: a LocalMapper's consecutive BA windows share most
    observations. A factor is immutable and fixed by its row (keyframe, point, measurement, stereo flag, sigma)
    and the builder's camera and Huber threshold, so a reused factor is the one that would be built (the same
    graph, the same estimate bit for bit). Holds the last window only; pickles as an empty cache (gtsam objects
    do not travel to a worker process, which keeps its own)."""

    def __init__(self) -> None:
        self._settings: tuple | None = None
        self._builder: FactorBuilder | None = None
        self._forget()

    def __reduce__(self):
        return (FactorCache, ())

    def __len__(self) -> int:
        return len(self._factors)

    def builder(self, camera, huber_k: float) -> FactorBuilder:
        """The builder of these settings (its noise models reused); other settings drop the cached factors."""
        settings = (camera, float(huber_k))
        if self._builder is None or self._settings != settings:
            self._settings, self._builder = settings, FactorBuilder(camera, huber_k)
            self._forget()
        return self._builder

    def factors(self, camera, huber_k: float, kf: np.ndarray, pt: np.ndarray, meas: np.ndarray, stereo: np.ndarray,
                sigma: np.ndarray) -> list[gtsam.NonlinearFactor]:
        """``FactorBuilder(camera, huber_k).factors(...)``, the rows of the previous call's window reused."""
        builder = self.builder(camera, huber_k)
        pair = _pair_keys(kf, pt)
        row = _row_bits(meas, stereo, sigma)
        src = self._lookup(pair, row)
        miss = src < 0
        new = iter(builder.factors(kf[miss], pt[miss], meas[miss], stereo[miss], sigma[miss]))
        prev = self._factors
        out = [prev[s] if s >= 0 else next(new) for s in src.tolist()]
        self._remember(pair, row, out)
        return out

    def _forget(self) -> None:
        self._sorted = np.zeros(0, np.int64)  # (kf, point) keys of the cached rows, sorted
        self._order = np.zeros(0, np.int64)  # their positions in _factors
        self._rows = np.zeros((0, 5), np.int64)
        self._factors: list[gtsam.NonlinearFactor] = []

    def _remember(self, pair: np.ndarray | None, row: np.ndarray, factors: list) -> None:
        if pair is None:
            self._forget()
            return
        self._order = np.argsort(pair, kind="stable")
        self._sorted, self._rows, self._factors = pair[self._order], row, factors

    def _lookup(self, pair: np.ndarray | None, row: np.ndarray) -> np.ndarray:
        """(N,) position of each row's factor among the cached ones, -1 where none is (or it differs in any bit)."""
        src = np.full(row.shape[0], -1, np.int64)
        if pair is None or self._sorted.size == 0:
            return src
        pos = np.minimum(np.searchsorted(self._sorted, pair), self._sorted.size - 1)
        cand = self._order[pos]
        hit = (self._sorted[pos] == pair) & (self._rows[cand] == row).all(axis=1)
        src[hit] = cand[hit]
        return src


def symbol_keys(char: str, ids: np.ndarray) -> list[int]:
    """``gtsam.Symbol(char, id).key()`` of each id as Python ints (the character is the key's top byte): one numpy
    pass instead of a ``X`` / ``L`` call per factor."""
    ids = np.asarray(ids, np.int64).reshape(-1)
    if ids.size and (ids.min() < 0 or ids.max() >= 1 << 56):
        shorthand = X if char == "x" else L if char == "l" else None
        if shorthand is None:
            raise ValueError(f"symbol_keys: no shorthand for {char!r}")
        return [shorthand(i) for i in ids.tolist()]  # GTSAM's own error for an id out of range
    return (np.uint64(ord(char)) << np.uint64(56) | ids.astype(np.uint64)).tolist()


def _pair_keys(kf: np.ndarray, pt: np.ndarray) -> np.ndarray | None:
    """One int64 per (keyframe id, point id), None if an id is out of [0, 2^31) (the cache is then not used)."""
    kf, pt = np.asarray(kf, np.int64), np.asarray(pt, np.int64)
    if kf.size and (min(kf.min(), pt.min()) < 0 or max(kf.max(), pt.max()) >= 1 << 31):
        return None
    return kf << 31 | pt


def _row_bits(meas: np.ndarray, stereo: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(N,5) int64: the bits of (uL, v, uR, sigma) and the stereo flag, compared exactly (NaN, -0.0 included)."""
    vals = np.column_stack([np.asarray(meas, np.float64).reshape(-1, 3), np.asarray(sigma, np.float64).reshape(-1)])
    return np.column_stack([vals.view(np.int64), np.asarray(stereo, np.int64).reshape(-1)])


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
    return a constant error with a zero Jacobian and the point is stuck for good. On the ``bench_ba`` window
    these settings reach a far lower cost in less time than the defaults, with equal or smaller pose error
    (docs/backend.md, "Fixed keyframes and LM damping").
    """
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(int(max_iterations))
    p.setRelativeErrorTol(1e-6)  # a relative decrease below 1e-6 moves nothing measurable
    p.setAbsoluteErrorTol(1e-10)
    p.setlambdaInitial(1.0)
    p.setUseFixedLambdaFactor(False)
    p.setVerbosityLM("SILENT")
    return p
