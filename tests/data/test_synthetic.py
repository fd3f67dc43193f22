"""Synthetic sequences: exact geometry, exact IMU, masks, determinism, options and disk layouts."""

from __future__ import annotations

import dataclasses
import logging
import pickle
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from vslam.config import from_dict
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence, write_sequence
from vslam.data.synthetic.motion import GRAVITY
from vslam.data.synthetic.render import Renderer
from vslam.data.synthetic.scene import CLEARANCE, PAD, Mover, _AtlasBuilder, _Strip
from vslam.data.types import PinholeCamera
from vslam.errors import ConfigError
from vslam.geometry.se3 import inv_T, make_T, so3_exp, so3_log

logger = logging.getLogger(__name__)

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5)  # same field of view as 640x480, 4x fewer rays


@pytest.fixture(scope="module")
def static_room() -> SyntheticSequence:
    return SyntheticSequence(SyntheticConfig(n_frames=90, n_movers=0))


@pytest.fixture(scope="module")
def busy_room() -> SyntheticSequence:
    return SyntheticSequence(SyntheticConfig(n_frames=300, n_movers=3, **SMALL))


# ----------------------------------------------------------------------------- geometry


def _inv_depth_bilinear(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at sub-pixel uv (N,2) by bilinear interpolation of 1/depth (exact on a plane)."""
    x0, y0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
    inv = 1.0 / depth.astype(np.float64)
    val = (
        inv[y0, x0] * (1 - fx) * (1 - fy) + inv[y0, x0 + 1] * fx * (1 - fy)
        + inv[y0 + 1, x0] * (1 - fx) * fy + inv[y0 + 1, x0 + 1] * fx * fy
    )
    return 1.0 / val


def _marker_checks(seq: SyntheticSequence, image: np.ndarray, T_world_cam: np.ndarray, cam: PinholeCamera):
    """(projected uv, dark-blob centroid, camera-frame z) of the markers seen well enough to measure."""
    pts = seq.landmarks()
    scene = seq.scene
    on_face = (np.abs(pts - scene.lo) < 1e-9) | (np.abs(pts - scene.hi) < 1e-9)
    normals = on_face.astype(float)
    pc = (inv_T(T_world_cam) @ np.c_[pts, np.ones(len(pts))].T).T[:, :3]
    ray = pts - T_world_cam[:3, 3]
    cos = np.abs(np.sum(normals * ray, axis=1)) / np.linalg.norm(ray, axis=1)
    z = pc[:, 2]
    ok = (z > 0.8) & (z < 4.0) & (cos > 0.75)
    uv = np.full((len(pts), 2), -1.0)
    uv[ok] = cam.project(pc[ok])
    ok &= (uv[:, 0] > 15) & (uv[:, 0] < cam.width - 16) & (uv[:, 1] > 15) & (uv[:, 1] < cam.height - 16)
    grey = 255.0 - cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)
    yy, xx = np.mgrid[0 : cam.height, 0 : cam.width]
    out = []
    for i in np.flatnonzero(ok):
        # Window inside the white ring (r 9 cm) holding the whole black dot (r 3 cm), foreshortening included.
        rad = cos[i] * 0.06 * cam.fx / z[i]
        u, v = uv[i]
        sl = (slice(int(v - rad - 2), int(v + rad + 3)), slice(int(u - rad - 2), int(u + rad + 3)))
        w = grey[sl] * ((xx[sl] - u) ** 2 + (yy[sl] - v) ** 2 <= rad**2)
        centroid = np.array([(w * xx[sl]).sum(), (w * yy[sl]).sum()]) / w.sum()
        out.append((uv[i], centroid, z[i]))
    return out


def test_markers_project_onto_their_rendered_dots(static_room: SyntheticSequence) -> None:
    seq, cam = static_room, static_room.calibration.cam0
    errors, depth_errors = [], []
    for i in (0, 29, 58, 89):
        r = seq.render(i)
        for cam_T, img in ((r.T_world_cam, r.image), (r.T_world_cam @ seq.calibration.T_cam0_cam1, r.right)):
            for uv, centroid, z in _marker_checks(seq, img, cam_T, cam):
                errors.append(np.linalg.norm(centroid - uv))
                if img is r.image:
                    depth_errors.append(abs(_inv_depth_bilinear(r.depth, uv[None])[0] - z))
    logger.info("markers: %d checked, max reprojection %.3f px, max depth error %.2e m", len(errors), max(errors), max(depth_errors))
    assert len(errors) >= 20
    assert max(errors) < 0.25  # spec: 0.5 px; 0.25 so that a half-texel slip (~0.55 px at 2.5 m) fails clearly
    assert max(depth_errors) < 1e-3


def test_depth_is_consistent_across_views(busy_room: SyntheticSequence) -> None:
    seq = busy_room
    cam = seq.calibration.cam0
    for i, j in ((10, 25), (100, 120)):
        ri, rj = seq.render(i, movers=False, right=False), seq.render(j, movers=False, right=False)
        vv, uu = np.mgrid[0 : cam.height : 3, 0 : cam.width : 3]
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
        p_i = cam.backproject(uv, ri.depth[vv.ravel(), uu.ravel()])
        T_j_i = inv_T(rj.T_world_cam) @ ri.T_world_cam
        p_j = p_i @ T_j_i[:3, :3].T + T_j_i[:3, 3]
        uv_j = cam.project(p_j)
        inside = (uv_j[:, 0] >= 0) & (uv_j[:, 0] < cam.width - 1) & (uv_j[:, 1] >= 0) & (uv_j[:, 1] < cam.height - 1)
        assert inside.mean() > 0.3, "the views should overlap"
        rel = np.abs(_inv_depth_bilinear(rj.depth, uv_j[inside]) - p_j[inside, 2]) / p_j[inside, 2]
        # Exact up to float32, except where the 2x2 interpolation cell straddles a room edge.
        assert np.mean(rel < 1e-4) > 0.98
        assert np.median(rel) < 1e-5


def test_masks_are_exactly_the_movers(busy_room: SyntheticSequence) -> None:
    seq, checked = busy_room, 0
    for i in range(0, len(seq), 15):
        r, static = seq.render(i), seq.render(i, movers=False)
        changed = r.depth != static.depth
        np.testing.assert_array_equal(changed, r.mask)
        assert np.array_equal(r.image[~r.mask], static.image[~r.mask]), "movers must change only their own pixels"
        assert np.all(r.depth[r.mask] < static.depth[r.mask]), "a mover is in front of the wall it hides"
        covered = np.zeros_like(r.mask)
        for x1, y1, x2, y2 in r.boxes.astype(int):
            box = r.mask[y1 : y2 + 1, x1 : x2 + 1]
            assert box[0].any() and box[-1].any() and box[:, 0].any() and box[:, -1].any(), "boxes are tight"
            covered[y1 : y2 + 1, x1 : x2 + 1] = True
        assert not np.any(r.mask & ~covered), "boxes bound the mask"
        checked += int(r.mask.sum() > 200)
    assert checked >= 3, "movers should be visible in several frames"


def test_renderer_z_buffers_movers_exactly(static_room: SyntheticSequence) -> None:
    """Known answers: camera at (0, 0, 1) looking down +x at two boxes in line, the room wall at x = 4."""

    def person(x: float, half: float) -> Mover:
        zero = np.zeros(3)
        return Mover(np.array([2 * half, 2 * half, 1.7]), np.array([x, 0.0, 0.85]), zero, zero, zero, 0.0, 0.0, 0.0)

    near, far = person(1.5, 0.25), person(2.5, 0.5)
    cam = PinholeCamera(64, 48, 52.5, 52.5, 31.5, 23.5)
    T = make_T(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.0, 0.0, 1.0]))
    for movers in ([near, far], [far, near]):
        view = Renderer(dataclasses.replace(static_room.scene, movers=movers), cam).render(T, 0.0)
        id_near, id_far = (1, 2) if movers[0] is near else (2, 1)
        assert view.depth[23, 31] == np.float32(1.25) and view.obj[23, 31] == id_near  # near face at x = 1.25
        assert view.depth[23, 43] == np.float32(2.0) and view.obj[23, 43] == id_far  # beside near, on far's face
        assert view.depth[23, 0] == np.float32(4.0) and view.obj[23, 0] == 0  # the wall
    static = Renderer(static_room.scene, cam).render(T, 0.0)
    assert static.depth[23, 31] == np.float32(4.0) and not static.obj.any()
    # A mover's texture rides with it: moving 1.25/52.5 m to the camera's right shifts its face by 1 px.
    walker = dataclasses.replace(near, vel=np.array([0.0, -1.25 / 52.5, 0.0]), face_x=np.arange(6) * 40.0 + 5, face_y=np.full(6, 5.0))
    renderer = Renderer(dataclasses.replace(static_room.scene, movers=[walker]), cam)
    v0, v1 = renderer.render(T, 0.0), renderer.render(T, 1.0)
    inside = v0.obj[:, 1:-1] & v1.obj[:, 2:]  # columns of the face seen at both times
    assert inside.sum() > 50
    diff = np.abs(v0.image[:, 1:-1].astype(int) - v1.image[:, 2:].astype(int))[inside.astype(bool)]
    assert diff.max() <= 2


def test_movers_keep_clear_of_the_cameras(busy_room: SyntheticSequence) -> None:
    seq = busy_room
    gt = seq.groundtruth()
    tau = gt.timestamps - seq.cfg.start_time
    cams = np.stack([gt.positions, (gt.poses @ seq.calibration.T_cam0_cam1)[:, :3, 3]], axis=1)
    assert len(seq.scene.movers) == 3
    for m in seq.scene.movers:
        gap = np.abs(cams - m.centre_at(tau)[:, None]) - m.size / 2
        assert np.all(np.any(gap >= CLEARANCE - 1e-9, axis=-1))
        assert np.all(m.centre_at(tau)[:, 2] == m.size[2] / 2), "movers walk on the floor"


# ----------------------------------------------------------------------------- IMU


def _integrate(seq: SyntheticSequence, k0: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Strapdown integration from the true state at sample k0 over n steps with the true biases
    removed; trapezoid on the world acceleration, midpoint on the gyro (both O(dt^2))."""
    imu, truth = seq.imu(), seq.imu_truth()
    gyro, accel = imu.gyro - truth.gyro_bias, imu.accel - truth.accel_bias
    R, p, v = truth.T_world_body[k0, :3, :3], truth.T_world_body[k0, :3, 3], truth.v_world[k0]
    for k in range(k0, k0 + n):
        dt = imu.t[k + 1] - imu.t[k]
        R1 = R @ so3_exp(0.5 * (gyro[k] + gyro[k + 1]) * dt)
        a0, a1 = R @ accel[k] + GRAVITY, R1 @ accel[k + 1] + GRAVITY
        p = p + v * dt + (2 * a0 + a1) / 6 * dt**2
        v = v + 0.5 * (a0 + a1) * dt
        R = R1
    T_true = truth.T_world_body[k0 + n]
    return np.linalg.norm(p - T_true[:3, 3]), np.degrees(np.linalg.norm(so3_log(T_true[:3, :3].T @ R)))


@pytest.mark.parametrize("scene", ["room", "street"])
def test_noise_free_imu_integrates_to_ground_truth(scene: str) -> None:
    seq = SyntheticSequence(SyntheticConfig(scene=scene, n_frames=75, imu_noise_enabled=False, n_movers=0, **SMALL))
    for k0 in (0, 150):
        dp, dr = _integrate(seq, k0, 200)  # 1 s at 200 Hz
        assert dp < 0.01 and dr < 0.1, (dp, dr)
        assert dp < 1e-3 and dr < 1e-3, "a second-order scheme on exact data is far better than the spec"


def test_imu_agrees_with_gtsam_preintegration(static_room: SyntheticSequence) -> None:
    gtsam = pytest.importorskip("gtsam")
    seq = SyntheticSequence(SyntheticConfig(n_frames=60, imu_noise_enabled=False, n_movers=0, **SMALL))
    imu, truth = seq.imu(), seq.imu_truth()
    params = gtsam.PreintegrationParams.MakeSharedU(-GRAVITY[2])  # gravity along -z: the vslam world
    params.setAccelerometerCovariance(np.eye(3) * 1e-6)
    params.setGyroscopeCovariance(np.eye(3) * 1e-8)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    bias = gtsam.imuBias.ConstantBias(truth.accel_bias[0], truth.gyro_bias[0])
    pim = gtsam.PreintegratedImuMeasurements(params, bias)
    k0, n = 20, 200
    for k in range(k0, k0 + n):  # averaged neighbours: GTSAM holds each sample over its interval
        pim.integrateMeasurement(0.5 * (imu.accel[k] + imu.accel[k + 1]), 0.5 * (imu.gyro[k] + imu.gyro[k + 1]), imu.t[k + 1] - imu.t[k])
    T0 = truth.T_world_body[k0]
    state = gtsam.NavState(gtsam.Rot3(T0[:3, :3]), gtsam.Point3(*T0[:3, 3]), truth.v_world[k0])
    pred = pim.predict(state, bias)
    T1 = truth.T_world_body[k0 + n]
    assert np.linalg.norm(pred.position() - T1[:3, 3]) < 0.01
    assert np.degrees(np.linalg.norm(so3_log(T1[:3, :3].T @ pred.attitude().matrix()))) < 0.1


def test_noisy_imu_matches_its_noise_model() -> None:
    cfg = SyntheticConfig(n_frames=90, n_movers=0, seed=3, **SMALL)
    seq = SyntheticSequence(cfg)
    imu, truth = seq.imu(), seq.imu_truth()
    dt = 1.0 / cfg.imu_rate
    f_body = np.einsum("nji,nj->ni", truth.T_world_body[:, :3, :3], truth.a_world - GRAVITY)
    white_g = imu.gyro - truth.omega_body - truth.gyro_bias
    white_a = imu.accel - f_body - truth.accel_bias
    n = cfg.imu_noise
    assert np.std(white_g) == pytest.approx(n.gyro_noise_density / np.sqrt(dt), rel=0.1)
    assert np.std(white_a) == pytest.approx(n.accel_noise_density / np.sqrt(dt), rel=0.1)
    assert np.std(np.diff(truth.gyro_bias, axis=0)) == pytest.approx(n.gyro_random_walk * np.sqrt(dt), rel=0.1)
    assert np.std(np.diff(truth.accel_bias, axis=0)) == pytest.approx(n.accel_random_walk * np.sqrt(dt), rel=0.1)
    np.testing.assert_allclose(truth.gyro_bias[0], cfg.gyro_bias)
    dp, dr = _integrate(seq, 100, 200)
    # 1 s of white accel noise: sigma_p ~ 2e-3 * sqrt(1/3) m; 8 sigma.
    assert dp < 0.01 and dr < 0.05, (dp, dr)


def test_accelerometer_measures_specific_force_with_gravity_up() -> None:
    seq = SyntheticSequence(SyntheticConfig(n_frames=120, imu_noise_enabled=False, n_movers=0, **SMALL))
    imu, truth = seq.imu(), seq.imu_truth()
    R = truth.T_world_body[:, :3, :3]
    f_world = np.einsum("nij,nj->ni", R, imu.accel - truth.accel_bias)
    # Over the sequence the mean acceleration is (v_end - v_start) / T: what remains is +g "up".
    T = imu.t[-1] - imu.t[0]
    mean_a = (truth.v_world[-1] - truth.v_world[0]) / T
    np.testing.assert_allclose(f_world.mean(axis=0) - mean_a, [0.0, 0.0, 9.81], atol=0.02)
    # And accelerations from twice-differenced ground-truth positions agree sample by sample.
    p = truth.T_world_body[:, :3, 3]
    a_num = (p[2:] - 2 * p[1:-1] + p[:-2]) / np.diff(imu.t[:2]) ** 2
    np.testing.assert_allclose(f_world[1:-1] + GRAVITY, a_num, atol=0.01)


def test_frames_partition_the_imu_stream(static_room: SyntheticSequence) -> None:
    seq = static_room
    t = np.concatenate([seq.frame_imu(i).t for i in range(len(seq))])
    all_t = seq.imu().t
    np.testing.assert_array_equal(t, all_t[all_t <= seq.timestamps()[-1]])
    assert len(seq.frame_imu(0)) == 1 and seq.frame_imu(0).t[0] == seq.timestamps()[0]


# ----------------------------------------------------------------------------- options


def test_same_seed_same_bytes_other_seed_other_data() -> None:
    cfg = SyntheticConfig(n_frames=10, lighting_change=True, **SMALL)
    a, b = SyntheticSequence(cfg), SyntheticSequence(cfg)
    c = SyntheticSequence(dataclasses.replace(cfg, seed=1))
    fa, fb, fc = a.frame(7), b.frame(7), c.frame(7)
    for name in ("image", "depth", "right", "dynamic_mask"):
        np.testing.assert_array_equal(getattr(fa, name), getattr(fb, name))
    np.testing.assert_array_equal(a.imu().accel, b.imu().accel)
    np.testing.assert_array_equal(a.groundtruth().poses, b.groundtruth().poses)
    assert not np.array_equal(fa.image, fc.image)
    assert not np.array_equal(a.imu().gyro, c.imu().gyro)
    assert not np.allclose(a.groundtruth().poses, c.groundtruth().poses)


def test_scene_is_built_where_frames_are_rendered_and_not_pickled() -> None:
    """Issue 41: the tracking process never renders when the front end is a child, so it must not hold the scene
    (a 590 m street's atlas is 283 MB), and the child gets the sequence without it and builds the same bytes."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=12, **SMALL))
    seq.groundtruth(), seq.imu(), seq.timestamps()
    assert seq._scene is None  # ground truth, IMU and times need no scene
    small = len(pickle.dumps(seq, protocol=pickle.HIGHEST_PROTOCOL))
    frame = seq.frame(5)
    assert seq._scene is not None
    assert len(pickle.dumps(seq, protocol=pickle.HIGHEST_PROTOCOL)) == small < seq.scene.atlas.nbytes / 4
    copy = pickle.loads(pickle.dumps(seq))
    again = copy.frame(5)
    for name in ("image", "depth", "dynamic_mask", "boxes"):
        np.testing.assert_array_equal(getattr(again, name), getattr(frame, name))
    np.testing.assert_array_equal(copy.landmarks(), seq.landmarks())


def test_street_atlas_paints_tile_rows_in_place() -> None:
    """A street face is a row of tiles made of 4 variants; the atlas builder paints it into the final image, with
    the same bytes (texels and replicated border) as packing the whole row as one image."""
    rng = np.random.default_rng(0)
    variants = [rng.integers(0, 255, (5, 7, 3), dtype=np.uint8) for _ in range(4)]
    order = np.array([2, 0, 0, 3, 1])
    small = rng.integers(0, 255, (4, 3, 3), dtype=np.uint8)
    for width in (35, 30, 29):  # whole tiles, a tile cut at its start, mid-tile
        packed, strip = _AtlasBuilder(40), _AtlasBuilder(40)
        full = np.concatenate([variants[v] for v in order], axis=1)[:, :width]
        for b, face in ((packed, full), (strip, _Strip(variants, order, width))):
            assert [b.add(small), b.add(small), b.add(face)] == [(1.0, 1.0), (6.0, 1.0), (1.0, 7.0)]  # 2 shelves
        expected = np.zeros((13, 37, 3), np.uint8)
        for x, y, p in ((0, 0, small), (5, 0, small), (0, 6, full)):
            padded = cv2.copyMakeBorder(p, PAD, PAD, PAD, PAD, cv2.BORDER_REPLICATE)
            expected[y : y + padded.shape[0], x : x + padded.shape[1]] = padded
        np.testing.assert_array_equal(packed.build(), expected[:, : width + 2])
        np.testing.assert_array_equal(strip.build(), expected[:, : width + 2])


def test_blackout_frames_are_black() -> None:
    seq = SyntheticSequence(SyntheticConfig(n_frames=8, blackouts=((3, 2),), **SMALL), sensor="stereo")
    np.testing.assert_array_equal(seq.blackout_frames(), [3, 4])
    frames = list(seq)
    for f in frames[3:5]:
        assert not f.image.any() and not f.right.any() and not f.depth.any()
        assert f.T_world_cam is not None and len(f.imu) > 0, "ground truth and IMU continue through a blackout"
    for f in frames[2], frames[5]:
        assert f.image.mean() > 20 and np.all(f.depth > 0)


def test_blurred_frames_lose_detail_but_keep_depth() -> None:
    cfg = SyntheticConfig(n_frames=4, blurs=((1, 2),), blur_sigma=4.0, **SMALL)
    sharp, blurred = SyntheticSequence(dataclasses.replace(cfg, blurs=()), sensor="stereo"), SyntheticSequence(cfg, sensor="stereo")
    for i in range(4):
        a, b = sharp.frame(i), blurred.frame(i)
        np.testing.assert_array_equal(a.depth, b.depth)
        if i in (1, 2):  # high-frequency energy (Laplacian variance) drops by an order of magnitude
            lap = [cv2.Laplacian(cv2.cvtColor(x, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var() for x in (a.image, b.image, b.right)]
            assert lap[1] < 0.1 * lap[0] and lap[2] < 0.1 * lap[0]
            np.testing.assert_array_equal(b.image, cv2.GaussianBlur(a.image, (0, 0), 4.0))
        else:
            np.testing.assert_array_equal(a.image, b.image)
    with pytest.raises(ConfigError, match="blur_sigma"):
        SyntheticConfig(blur_sigma=0.0)
    with pytest.raises(ConfigError, match="blurs"):
        SyntheticConfig(blurs=((-1, 2),))


def test_lighting_change_varies_brightness_over_time() -> None:
    base = dict(n_frames=90, n_movers=0, **SMALL)
    lit, plain = SyntheticSequence(SyntheticConfig(lighting_change=True, **base)), SyntheticSequence(SyntheticConfig(**base))
    ratios = []
    for i in (0, 30, 60, 89):
        a, b = lit.render(i, right=False), plain.render(i, right=False)
        np.testing.assert_array_equal(a.depth, b.depth)  # only the photometry changes
        ratios.append(a.image.mean() / b.image.mean())
    assert max(ratios) - min(ratios) > 0.05, ratios
    assert plain.lighting(10) == (1.0, 1.0)


def test_poor_light_dims_and_adds_seeded_read_noise_to_both_cameras_only() -> None:
    base = dict(n_frames=3, n_movers=0, **SMALL)
    plain = SyntheticSequence(SyntheticConfig(**base), sensor="stereo")
    dim = SyntheticSequence(SyntheticConfig(exposure=0.25, image_noise=2.0, **base), sensor="stereo")
    a, b = plain.render(1), dim.render(1)
    np.testing.assert_array_equal(a.depth, b.depth)
    for clean, noisy in ((a.image, b.image), (a.right, b.right)):
        err = noisy.astype(np.float64) - 0.25 * clean
        interior = (clean > 8) & (clean < 250)  # away from clipping
        assert abs(err[interior].mean()) < 0.1 and 1.8 < err[interior].std() < 2.2
    assert not np.array_equal(b.image - np.round(0.25 * a.image.astype(np.float32)).astype(np.uint8),
                              b.right - np.round(0.25 * a.right.astype(np.float32)).astype(np.uint8))
    np.testing.assert_array_equal(b.image, dim.render(1).image)  # seeded per frame and camera: same on a re-render
    assert not np.array_equal(dim.render(0).image.astype(int) - 0.25 * plain.render(0).image,
                              b.image.astype(int) - 0.25 * a.image)  # a new draw every frame
    for field, bad in (("exposure", 0.0), ("image_noise", -1.0)):
        with pytest.raises(ConfigError, match=field):
            SyntheticConfig(**{field: bad})


@pytest.mark.parametrize("scene", ["room", "street"])
def test_loop_returns_to_start_and_open_path_does_not(scene: str) -> None:
    for loop in (True, False):
        # 15 s: long enough that an open room path must be sized not to come back.
        seq = SyntheticSequence(SyntheticConfig(scene=scene, n_frames=450, loop=loop, n_movers=0, width=32, height=24, fx=26.25, fy=26.25))
        pos = seq.groundtruth().positions
        later = np.linalg.norm(pos[len(pos) // 2 :] - pos[0], axis=1)
        if loop:  # back at the start, up to half a frame of travel
            assert later.min() < 0.6 * seq.cfg.mean_speed / seq.cfg.fps + 0.01, later.min()
        else:
            assert later.min() > 0.5, later.min()


def test_low_texture_has_fewer_corners() -> None:
    base = dict(n_frames=30, n_movers=0, **SMALL)
    orb = cv2.ORB_create(5000)
    counts = {}
    for low in (False, True):
        seq = SyntheticSequence(SyntheticConfig(low_texture=low, **base))
        counts[low] = np.mean([len(orb.detect(cv2.cvtColor(seq.render(i, right=False).image, cv2.COLOR_BGR2GRAY))) for i in (0, 15, 29)])
    assert counts[False] > 300, "textures must feed ORB"
    assert counts[True] < 0.5 * counts[False], counts


def test_room_camera_keeps_away_from_walls_and_sees_1_to_6_m() -> None:
    seq = SyntheticSequence(SyntheticConfig(n_frames=300, n_movers=0, width=64, height=48, fx=52.5, fy=52.5))
    pos = seq.groundtruth().positions
    assert np.all(pos - seq.scene.lo >= 0.8) and np.all(seq.scene.hi - pos >= 0.8)
    depths = np.concatenate([seq.render(i, right=False).depth.ravel() for i in range(0, 300, 20)])
    assert np.percentile(depths, 2) > 0.9 and np.percentile(depths, 98) < 6.5


def test_sensor_choice_and_calibration() -> None:
    seq = SyntheticSequence(SyntheticConfig(n_frames=4, baseline=0.12, **SMALL), sensor="stereo")
    assert seq.sensor == "stereo" and len(seq) == 4
    f = seq.frame(1)
    assert f.right is not None and f.depth is not None and f.image.shape == (240, 320, 3)
    cal = seq.calibration
    assert cal.baseline == pytest.approx(0.12) and cal.depth_scale == 5000.0
    np.testing.assert_allclose(cal.T_cam0_cam1[:3, 3], [0.12, 0.0, 0.0], atol=1e-12)
    assert (cal.cam0.cx, cal.cam0.cy) == (159.5, 119.5)
    # Camera z (forward) is body x (forward), camera y (down) is body -z, within a few degrees.
    assert cal.T_body_cam0[:3, :3] @ [0, 0, 1] @ [1, 0, 0] > np.cos(np.radians(3))
    assert cal.T_body_cam0[:3, :3] @ [0, 1, 0] @ [0, 0, -1] > np.cos(np.radians(3))
    # Frame 3 (0.1 s) and IMU sample 20 coincide: cam0 pose = body pose * T_body_cam0.
    np.testing.assert_allclose(seq.groundtruth().poses[3], seq.imu_truth().T_world_body[20] @ cal.T_body_cam0, atol=1e-12)
    with pytest.raises(ValueError):
        SyntheticSequence(SyntheticConfig(n_frames=2), sensor="lidar")  # type: ignore[arg-type]


def test_config_loads_from_a_plain_dict() -> None:
    cfg = from_dict(SyntheticConfig, {"scene": "street", "blackouts": [[1, 2]], "imu_noise": {"gyro_noise_density": 1e-3}, "gyro_bias": [0, 0, 0]})
    assert cfg.blackouts == ((1, 2),) and cfg.imu_noise.gyro_noise_density == 1e-3 and cfg.mean_speed == 5.0


# ----------------------------------------------------------------------------- disk layouts


def _data_lines(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]


def test_write_sequence_layouts(tmp_path: Path) -> None:
    seq = SyntheticSequence(SyntheticConfig(n_frames=5, scene="street", width=160, height=120, fx=131.25, fy=131.25))
    roots = write_sequence(seq, tmp_path)
    tum, mav0 = roots["tum"], roots["asl"]
    assert tum == tmp_path / "rgbd" and mav0 == tmp_path / "mav0"
    for sub in ("rgb", "depth", "mask"):
        assert len(list((tum / sub).glob("*.png"))) == 5
        lines = (tum / f"{sub}.txt").read_text().splitlines()
        assert [ln.startswith("#") for ln in lines[:4]] == [True, True, True, False] and len(lines) == 8
    gt = _data_lines(tum / "groundtruth.txt")
    assert len(gt) == 5 and len(gt[0].split()) == 8
    assert len(_data_lines(tum / "accelerometer.txt")) == len(seq.imu())
    boxes = _data_lines(tum / "boxes.txt")
    assert all(len(b.split()) == 6 for b in boxes)
    calib = yaml.safe_load((tum / "calibration.yaml").read_text())
    assert calib == dict(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5, distortion_model="none", distortion=[], depth_scale=5000.0)
    # Depth PNG round trip: 1/5000 m steps, 0 beyond the 16-bit range (street depths reach 100 m).
    name = _data_lines(tum / "depth.txt")[2].split()[1]
    raw = cv2.imread(str(tum / name), cv2.IMREAD_UNCHANGED)
    depth = seq.render(2, right=False).depth
    assert raw.dtype == np.uint16
    near = depth < 65535 / 5000.0
    assert np.all(np.abs(raw[near] / 5000.0 - depth[near]) <= 0.5 / 5000 + 1e-6) and np.all(raw[~near] == 0)

    for cam in ("cam0", "cam1"):
        assert len(list((mav0 / cam / "data").glob("*.png"))) == 5
        assert (mav0 / cam / "data.csv").read_text().splitlines()[0] == "#timestamp [ns],filename"
        text = (mav0 / cam / "sensor.yaml").read_text()
        assert text.startswith("%YAML:1.0\n")
        sensor = yaml.safe_load(text.split("\n", 1)[1])
        assert sensor["resolution"] == [160, 120] and sensor["intrinsics"] == [131.25, 131.25, 79.5, 59.5]
        assert sensor["camera_model"] == "pinhole" and sensor["distortion_model"] == "radial-tangential"
        T = np.array(sensor["T_BS"]["data"]).reshape(4, 4)
        np.testing.assert_allclose(T, getattr(seq.calibration, f"T_body_{cam}"), atol=1e-12)
    imu_lines = (mav0 / "imu0" / "data.csv").read_text().splitlines()
    assert imu_lines[0].startswith("#timestamp [ns],w_RS_S_x [rad s^-1]") and len(imu_lines) == len(seq.imu()) + 1
    imu_yaml = yaml.safe_load((mav0 / "imu0" / "sensor.yaml").read_text().split("\n", 1)[1])
    assert imu_yaml["rate_hz"] == 200 and imu_yaml["accelerometer_noise_density"] == pytest.approx(2.0e-3)
    state = _data_lines(mav0 / "state_groundtruth_estimate0" / "data.csv")
    assert len(state) == len(seq.imu()) and len(state[0].split(",")) == 17
    assert int(state[0].split(",")[0]) == seq.timestamps_ns()[0] > 1e12


def test_written_layouts_load_with_the_readers(tmp_path: Path) -> None:
    tum_mod = pytest.importorskip("vslam.data.tum")
    euroc_mod = pytest.importorskip("vslam.data.euroc")
    if not hasattr(tum_mod, "TumRgbdSequence") or not hasattr(euroc_mod, "EurocSequence"):
        pytest.skip("dataset readers not available")
    seq = SyntheticSequence(SyntheticConfig(n_frames=4, **SMALL))
    roots = write_sequence(seq, tmp_path)
    f, g = next(iter(tum_mod.TumRgbdSequence(roots["tum"]))), seq.frame(0)
    np.testing.assert_array_equal(f.image, g.image)
    assert np.abs(f.depth - g.depth).max() <= 1e-4
    np.testing.assert_allclose(f.T_world_cam, g.T_world_cam, atol=1e-6)
    np.testing.assert_array_equal(f.dynamic_mask, g.dynamic_mask)
    e = euroc_mod.EurocSequence(roots["asl"])
    assert len(e) == 4
    np.testing.assert_allclose(e.imu().accel, seq.imu().accel, atol=1e-9)
    np.testing.assert_allclose(e.calibration.T_body_cam1, seq.calibration.T_body_cam1, atol=1e-12)


def test_render_speed_is_logged() -> None:
    """Timing is logged, never asserted (machines are noisy); see render.py for the measured figure."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=10))
    seq.render(0)
    start = time.perf_counter()
    for i in range(1, 10):
        seq.render(i)
    logger.info("synthetic render: %.1f ms per 640x480 frame (left + depth + mask + boxes + right)", (time.perf_counter() - start) / 9 * 1e3)
