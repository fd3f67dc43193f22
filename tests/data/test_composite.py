"""make-dynamic: the composited masks and depths follow the billboards' projection geometry and occlusion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vslam.data.composite import Billboard, MakeDynamicConfig, composite, make_dynamic
from vslam.paths import data_root

K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
CUT = np.dstack([np.full((40, 20, 3), 200, np.uint8), np.full((40, 20), 255, np.uint8)])  # opaque 2:1 cutout


def _board(centre=(0.0, 0.0, 2.0), amp=0.0, direction=(1.0, 0, 0), omega=1.0, phase=0.0):
    return Billboard(CUT, np.array(centre), np.array([0.0, -1.0, 0.0]), 1.0, np.array(direction), amp, omega, phase)


def _scene(z):
    return np.zeros((120, 160, 3), np.uint8), np.full((120, 160), z, np.float32)


def test_frontal_billboard_mask_and_depth():
    img, dep = _scene(5.0)
    out, d, mask, boxes = composite(img, dep, K, np.eye(4), 0.0, [_board()])
    # corners x = +-0.25, y = +-0.5 at z = 2 -> u in [67.5, 92.5], v in [35, 85]
    ys, xs = np.nonzero(mask)
    assert xs.min() >= 67 and xs.max() <= 93 and ys.min() >= 34 and ys.max() <= 86
    assert mask[36:84, 69:91].all()
    np.testing.assert_allclose(d[mask], 2.0, atol=1e-5)
    np.testing.assert_array_equal(d[~mask], 5.0)
    assert (out[mask] == 200).all() and (out[~mask] == 0).all()
    np.testing.assert_array_equal(boxes, [[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]])


def test_occlusion_by_nearer_surface_and_invalid_depth():
    img, dep = _scene(1.5)  # the recorded surface is nearer than the billboard: nothing shows
    _, d, mask, boxes = composite(img, dep, K, np.eye(4), 0.0, [_board()])
    assert not mask.any() and len(boxes) == 0 and (d == 1.5).all()
    dep[:, 80:] = 5.0  # left half near, right half far
    dep[:, 120:] = 0.0  # invalid depth counts as far
    _, _, mask, _ = composite(img, dep, K, np.eye(4), 0.0, [_board(), _board(centre=(1.0, 0.0, 2.0))])
    assert not mask[:, :80].any() and mask[:, 80:93].any() and mask[:, 120:].any()


def test_masks_match_projection_geometry_for_a_moving_board_and_tilted_camera():
    rng = np.random.default_rng(0)
    b = _board(centre=(0.2, 0.1, 2.5), amp=0.3, omega=2.0, phase=0.3)
    for t in (0.0, 0.4, 0.9):
        a = rng.normal(0, 0.1, 3)
        Rx = np.array([[1, 0, 0], [0, np.cos(a[0]), -np.sin(a[0])], [0, np.sin(a[0]), np.cos(a[0])]])
        Ry = np.array([[np.cos(a[1]), 0, np.sin(a[1])], [0, 1, 0], [-np.sin(a[1]), 0, np.cos(a[1])]])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rx @ Ry, rng.normal(0, 0.1, 3)
        img, dep = _scene(6.0)
        _, d, mask, _ = composite(img, dep, K, T, t, [b])
        ys, xs = np.nonzero(mask)
        assert len(xs) > 300
        X_cam = (np.linalg.inv(K) @ np.vstack([xs, ys, np.ones_like(xs)])) * d[ys, xs]
        X = (T[:3, :3] @ X_cam).T + T[:3, 3]
        c = b.corners_world(t, T[:3, 3])
        centre = c.mean(0)
        np.testing.assert_allclose(centre, b.centre + 0.3 * np.sin(2.0 * t + 0.3) * b.direction, atol=1e-12)
        n = np.cross(c[1] - c[0], c[3] - c[0])
        n /= np.linalg.norm(n)
        assert np.abs((X - centre) @ n).max() < 1e-4  # every mask pixel's depth lies on the billboard's plane
        right, up = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0]), (c[0] - c[3]) / np.linalg.norm(c[0] - c[3])
        assert np.abs((X - centre) @ right).max() <= 0.25 + 0.03 and np.abs((X - centre) @ up).max() <= 0.5 + 0.03
        # the mask is the board's projected quadrilateral (pixel-rounding differences only)
        uvw = K @ np.linalg.inv(T)[:3] @ np.c_[c, np.ones(4)].T
        quad = np.zeros_like(mask, np.uint8)
        cv2.fillPoly(quad, [np.round((uvw[:2] / uvw[2]).T * 16).astype(np.int32)], 1, shift=4)
        quad = quad.astype(bool)
        assert (mask & quad).sum() / (mask | quad).sum() > 0.9


TEDDY = data_root() / "tum" / "rgbd_dataset_freiburg3_teddy"
COCO = data_root() / "coco128"


@pytest.mark.skipif(not (TEDDY.is_dir() and COCO.is_dir()), reason="TUM teddy / COCO128 not in $VSLAM_DATA")
def test_make_dynamic_on_teddy_reads_back(tmp_path):
    from vslam.data.tum import TumRgbdSequence

    out = make_dynamic(TEDDY, tmp_path / "teddy_dyn", COCO, MakeDynamicConfig(n_people=2, seed=1, max_frames=12))
    seq = TumRgbdSequence(out)
    frames = list(seq)
    assert len(frames) == 12
    with_gt = [f for f in frames if f.T_world_cam is not None]
    assert with_gt and all(f.dynamic_mask is not None for f in frames)
    assert any(f.dynamic_mask.any() for f in with_gt)
    assert not any(f.dynamic_mask.any() for f in frames if f.T_world_cam is None)  # no pose: left untouched
    for f in with_gt:
        if f.dynamic_mask.any():
            ys, xs = np.nonzero(f.dynamic_mask)
            b = f.boxes  # inclusive pixel boxes cover the mask
            assert len(b) >= 1 and b[:, 0].min() <= xs.min() and b[:, 2].max() >= xs.max()


@pytest.mark.skipif(not TEDDY.is_dir(), reason="TUM teddy not in $VSLAM_DATA")
def test_teddy_walkers_stand_along_the_mocap_vertical():
    from vslam.data.composite import world_up
    from vslam.data.tum import TumRgbdSequence

    up = world_up(TumRgbdSequence(TEDDY).groundtruth().poses)
    assert np.degrees(np.arccos(up[2])) < 5.0  # fr3's mocap z is up; the first camera's -y is 26 degrees off


def test_road_walkers_stand_on_the_road_ahead():
    """KITTI walkers: feet ``camera_height`` below the camera of the frame they belong to, 6-14 m ahead."""
    from vslam.data.composite import place_walkers_on_road

    poses = np.tile(np.eye(4), (40, 1, 1))
    poses[:, 2, 3] = np.arange(40) * 0.8  # driving along +z (camera y points down, KITTI convention)
    cfg = MakeDynamicConfig.for_kitti(n_people=4, seed=3)
    walkers = place_walkers_on_road([CUT], poses, cfg, np.random.default_rng(3))
    assert [f for f, _ in walkers] == [0, 10, 20, 30]
    for f, b in walkers:
        corners = b.corners_world(0.0, poses[f][:3, 3])
        feet_y = corners[2:, 1]  # bottom-right, bottom-left
        np.testing.assert_allclose(feet_y, cfg.camera_height, atol=1e-9)
        ahead = b.centre[2] - poses[f][2, 3]
        assert 6.0 <= ahead <= 14.0 and 1.0 <= abs(b.centre[0]) <= 4.0


def _circling_poses(pitch_deg: float, n: int = 60, roll_sd_deg: float = 1.5, seed: int = 0) -> np.ndarray:
    """A hand-held camera walking around the origin, looking at it and pitched down by ``pitch_deg``, small
    random roll; world z up (as TUM's mocap frame happens to be)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a = 2 * np.pi * 0.6 * k / n
        C = np.array([2 * np.cos(a), 2 * np.sin(a), 1.5])
        fwd_h = -C[:2] / np.linalg.norm(C[:2])
        p, r = np.radians(pitch_deg), np.radians(rng.normal(0, roll_sd_deg))
        z = np.r_[np.cos(p) * fwd_h, -np.sin(p)]
        x0 = np.cross(z, [0, 0, 1.0])
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(z, x0)
        x, y = np.cos(r) * x0 + np.sin(r) * y0, -np.sin(r) * x0 + np.cos(r) * y0
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.c_[x, y, z], C
        out.append(T)
    return np.array(out)


def test_world_up_is_gravity_not_the_pitched_first_camera():
    """The walkers stood along the first camera's -y: 25 degrees off vertical on TUM teddy, so they leaned and,
    seen from the side, lay tilted in the image (COCO detectors miss such people). Gravity comes from the plane
    the cameras' x axes span."""
    from vslam.data.composite import place_people, world_up

    poses = _circling_poses(25.0)
    up = world_up(poses)
    assert np.degrees(np.arccos(up @ [0, 0, 1.0])) < 2.0
    assert np.degrees(np.arccos(-poses[0][:3, 1] @ [0, 0, 1.0])) > 20.0  # what the walkers used to stand along
    boards = place_people([CUT], poses[0], MakeDynamicConfig(n_people=3, seed=2), np.random.default_rng(2), up, 0.0)
    for b in boards:
        np.testing.assert_allclose(b.up, up)
        assert abs(b.direction @ up) < 1e-9  # they walk level
        c = b.corners_world(0.3, poses[5][:3, 3])
        np.testing.assert_allclose(c[2:] @ up, 0.0, atol=1e-9)  # feet on the floor
    # a camera that never turns: no plane of x axes; its mean -y without the x component (no roll assumed)
    still = np.repeat(poses[:1], 10, axis=0)
    np.testing.assert_allclose(world_up(still), -poses[0][:3, 1], atol=1e-9)


def test_floor_height_is_the_lowest_surface_seen():
    from vslam.data.composite import floor_height

    from vslam.data.types import PinholeCamera

    cam = PinholeCamera(320, 240, 300.0, 300.0, 160.0, 120.0)
    T = np.eye(4)  # camera 1.5 m above a floor at world y = +1.5 (camera y down), looking along +z
    v, u = np.mgrid[0:240, 0:320]
    ray_y = (v - 120) / 300.0
    depth = np.where(ray_y > 0.05, 1.5 / np.maximum(ray_y, 1e-9), 0.0).astype(np.float32)  # floor below the horizon
    depth[depth > 10] = 0
    assert floor_height(depth, cam, T, np.array([0, -1.0, 0])) == pytest.approx(-1.5, abs=1e-3)
    assert floor_height(np.zeros((240, 320), np.float32), cam, T, np.array([0, -1.0, 0])) is None


KITTI07 = data_root() / "kitti" / "sequences" / "07"


@pytest.mark.skipif(not (KITTI07.is_dir() and COCO.is_dir()), reason="KITTI 07 / COCO128 not in $VSLAM_DATA")
def test_make_dynamic_on_kitti_reads_back_with_masks(tmp_path):
    from vslam.data.kitti import KittiSequence

    out = make_dynamic(KITTI07, tmp_path / "k", COCO, MakeDynamicConfig.for_kitti(n_people=2, seed=0, max_frames=8))
    assert out == tmp_path / "k" / "sequences" / "07"
    seq, src = KittiSequence(out), KittiSequence(KITTI07)
    assert len(seq) == 8
    np.testing.assert_allclose(seq.groundtruth().poses, src.groundtruth().poses[:8])
    seen = 0
    for i in range(8):
        f, g = seq.frame(i), src.frame(i)
        changed = f.image != g.image
        grown = cv2.dilate(f.dynamic_mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        assert not (changed & ~grown).any()  # the composite only touched the walkers
        seen += int(f.dynamic_mask.sum())
    assert seen > 1000  # the first walker is in view from frame 0
    rows = [ln.split() for ln in (out / "boxes.txt").read_text().splitlines() if not ln.startswith("#")]
    assert rows and all(len(r) == 6 for r in rows)
