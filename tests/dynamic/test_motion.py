"""Geometric consistency check: a moving object is flagged, a static instance of the same kind is kept."""

from __future__ import annotations

import numpy as np

from vslam.data.types import PinholeCamera
from vslam.dynamic import GeometricCheck, GeometricConfig

CAM = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)


def _scene(rng: np.random.Generator):
    """Background wall points, a 'person' that walks 4 cm/frame and an identical one that stands still."""
    bg = np.column_stack([rng.uniform(-2.5, 2.5, 400), rng.uniform(-1.5, 1.5, 400), rng.uniform(3.5, 4.5, 400)])
    body = np.column_stack([rng.uniform(-0.25, 0.25, 60), rng.uniform(-0.8, 0.8, 60), rng.uniform(-0.1, 0.1, 60)])
    mover0 = body + [-1.2, 0.0, 2.5]
    still = body[::-1] + [1.2, 0.0, 2.5]
    desc = rng.integers(0, 256, (520, 32), dtype=np.uint8)  # one fixed descriptor per 3-D point
    return bg, mover0, still, desc


def _observe(T_world_cam, Xw, desc, rng):
    Xc = (Xw - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    uv = CAM.project(Xc)
    depth = Xc[:, 2] + rng.normal(0, 0.004, len(Xc))  # 4 mm depth noise
    order = rng.permutation(len(Xw))  # keypoint order is arbitrary per frame
    return uv[order], depth[order], desc[order], order


def test_flags_the_mover_and_keeps_the_static_instance():
    rng = np.random.default_rng(5)
    bg, mover0, still, desc = _scene(rng)
    chk = GeometricCheck(GeometricConfig(enabled=True), CAM)
    cls = np.r_[np.zeros(400), np.ones(60), 2 * np.ones(60)].astype(int)  # 0 background, 1 mover, 2 still
    for k in range(14):
        T = np.eye(4)
        T[:3, 3] = [0.02 * k, 0.0, 0.01 * k]  # the camera moves too, and the check uses its (tracked) pose
        T[:3, 3] += rng.normal(0, 0.002, 3)  # tracking error
        Xw = np.vstack([bg, mover0 + [0.04 * k, 0.0, 0.0], still])
        uv, depth, d, order = _observe(T, Xw, desc, rng)
        if k >= 1:
            near = chk.in_region(uv, depth)  # the region flagged in the previous frame covers the mover now
        flagged = chk.check(T, uv, depth, d)
        c = cls[order]
        if k < 6:  # fewer past frames than min_votes gaps need: nothing can be flagged yet
            assert not flagged.any()
        else:
            assert flagged[c == 1].mean() >= 0.95, k
            assert not flagged[c == 2].any(), k  # the standing 'person'
            assert flagged[c == 0].mean() <= 0.01, k
            if k >= 7:
                assert near[c == 1].mean() >= 0.9 and not near[c == 2].any()


def test_one_bad_depth_or_match_is_not_enough():
    """Only one past frame disagrees (a depth glitch now would disagree with all, so shift one past frame):
    min_votes=2 of gaps (3, 6, 9) keeps the point."""
    rng = np.random.default_rng(1)
    bg, _, _, desc = _scene(rng)
    desc = desc[:400]
    chk = GeometricCheck(GeometricConfig(enabled=True), CAM)
    for k in range(10):
        T = np.eye(4)
        Xw = bg.copy()
        if k == 3:  # frame 3 (gap 6 from frame 9) saw every point 20 cm off
            Xw = Xw + [0.2, 0.0, 0.0]
        uv, depth, d, _ = _observe(T, Xw, desc, rng)
        flagged = chk.check(T, uv, depth, d)
    assert not flagged.any()
    votes, tested = chk.residual_votes(np.full((1, 3), np.nan), np.full(1, np.nan), desc[:1])
    assert votes.sum() == tested.sum() == 0  # no depth: no vote, no comparison


def test_static_detector_boxes_are_kept_and_moving_ones_masked():
    """keep_static_boxes: the box of the standing 'person' (a sitting person, or a false detection on a static
    object) is released once its keypoints were compared and showed no motion; the walker's box stays masked,
    also after the walker stops at frame 9 (moving_memory_s; with no memory it is released once its keypoints
    agree with frames 3 and 6 back). Off: both boxes stay masked."""
    from vslam.data.types import Frame
    from vslam.dynamic import DynamicConfig, DynamicFilter, in_boxes
    from vslam.dynamic.detector import Detections
    from vslam.features.base import Features

    def run(keep_static: bool, memory_s: float = 5.0, flag_points: bool = True,
            walker_boxed: bool = True) -> list[tuple[float, float, float]]:
        rng = np.random.default_rng(3)
        _, mover0, still, desc = _scene(rng)
        # a flat, richly textured wall: each box holds several times more static wall than person
        bg = np.column_stack([rng.uniform(-2.5, 2.5, 3000), rng.uniform(-1.5, 1.5, 3000), np.full(3000, 4.0)])
        desc = np.vstack([rng.integers(0, 256, (3000, 32), dtype=np.uint8), desc[400:]])
        cls = np.r_[np.zeros(3000), np.ones(60), 2 * np.ones(60)].astype(int)
        boxes: list[np.ndarray] = []

        class TwoBoxes:
            def detect(self, image):
                b = np.array(boxes if walker_boxed else boxes[1:])  # not boxed: the detector misses the walker
                return Detections(b, np.full(len(b), 0.9), np.zeros(len(b), np.int64), np.array(["person"] * len(b), dtype=object))

        geo = GeometricConfig(enabled=True, keep_static_boxes=keep_static, moving_memory_s=memory_s, flag_points=flag_points)
        flt = DynamicFilter(DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.0, geometric=geo), CAM, detector=TwoBoxes())
        out = []
        for k in range(20):
            T = np.eye(4)
            T[:3, 3] = [0.02 * k, 0.0, 0.01 * k]
            Xw = np.vstack([bg, mover0 + [0.04 * min(k, 9), 0.0, 0.0], still])
            uv, depth, d, order = _observe(T, Xw, desc, rng)
            px = np.rint(uv).astype(int)
            vis = (px[:, 0] >= 0) & (px[:, 0] < 640) & (px[:, 1] >= 0) & (px[:, 1] < 480)
            uv, depth, d, order, px = uv[vis], depth[vis], d[vis], order[vis], px[vis]
            img_depth = np.zeros((480, 640), np.float32)
            far_first = np.argsort(-depth)
            img_depth[px[far_first, 1], px[far_first, 0]] = depth[far_first]  # the nearest point owns its pixel
            vis = img_depth[px[:, 1], px[:, 0]] == depth.astype(np.float32)  # an occluded point is not detected
            uv, depth, d, order = uv[vis], depth[vis], d[vis], order[vis]
            c = cls[order]
            boxes[:] = [np.r_[uv[c == j].min(0) - 60, uv[c == j].max(0) + 60] for j in (1, 2)]  # loose boxes: mostly wall
            f = Features(uv, uv, d, np.zeros(len(uv)), np.ones(len(uv)))
            keep = flt.keep(Frame(k, k / 30, np.zeros((480, 640), np.uint8), depth=img_depth), f)
            flt.observe(T)
            outside = (c == 0) & ~in_boxes(uv, np.array(boxes))  # the wall outside both boxes
            out.append((keep[outside].mean(), keep[c == 1].mean(), keep[c == 2].mean()))
            if keep_static and memory_s > 0 and k >= 6 and walker_boxed:  # the verdict (the walker's flagged points are masked anyway)
                np.testing.assert_array_equal(flt.static_boxes, [boxes[1]])
        return out

    on, off, forgetful = run(True), run(False), run(True, memory_s=0.0)
    # flag_points=false: the same box verdicts; a walker the detector misses is flagged only with flag_points
    assert run(True, flag_points=False) == on
    missed, missed_unflagged = run(True, walker_boxed=False), run(True, flag_points=False, walker_boxed=False)
    assert [w for _, w, _ in missed[7:15]] == [0.0] * 8  # flagged while it walks (and 6 frames after)
    assert [w for _, w, _ in missed_unflagged] == [1.0] * 20
    assert [s for _, _, s in missed[8:]] == [s for _, _, s in missed_unflagged[8:]] == [1.0] * 12
    assert [w for _, w, _ in forgetful[:15]] == [0.0] * 15 and min(w for _, w, _ in forgetful[16:]) >= 0.95
    for k in range(20):
        assert off[k][1] == 0.0 and off[k][2] == 0.0, k  # boxes mask everything in them
        assert on[k][1] == 0.0, k  # the walker never gets out
        assert on[k][0] >= 0.99 and off[k][0] >= 0.99, k
        if k >= 7:  # compared against min_votes past frames from frame 6: released from the next frame on
            assert on[k][2] >= 0.95, k
        else:
            assert on[k][2] == 0.0, k


def test_region_is_every_keypoint_near_a_seed_in_the_image_and_in_depth():
    """``in_region``: within region_px of a flagged keypoint of the last frame and, where both have depth, within
    region_depth_m of its depth (a keypoint or seed without depth joins on the image distance alone)."""
    rng = np.random.default_rng(3)
    cfg = GeometricConfig(enabled=True, region_px=25.0, region_depth_m=0.3)
    geo = GeometricCheck(cfg, CAM)
    seed_uv, seed_z = rng.uniform(0, 640, (60, 2)), rng.uniform(0.5, 4.0, 60)
    seed_z[::7] = np.nan
    geo._region_uv, geo._region_z = seed_uv, seed_z
    uv = np.vstack([seed_uv[:40] + rng.normal(0, 10, (40, 2)), rng.uniform(0, 640, (400, 2))])
    z = np.concatenate([seed_z[:40] + rng.normal(0, 0.3, 40), rng.uniform(0.5, 4.0, 400)])
    z[::11] = np.nan
    d_px = np.linalg.norm(uv[:, None] - seed_uv[None], axis=2)
    dz = np.abs(z[:, None] - seed_z[None])
    expect = ((d_px <= 25.0) & (~np.isfinite(dz) | (dz <= 0.3))).any(axis=1)
    assert 20 < expect.sum() < 420  # both outcomes occur
    np.testing.assert_array_equal(geo.in_region(uv, z), expect)
    assert not geo.in_region(np.zeros((0, 2)), np.zeros(0)).size
    geo.reset()
    assert not geo.in_region(uv, z).any()


def test_box_verdicts_only_needs_the_box_verdicts():
    import pytest

    from vslam.errors import ConfigError

    with pytest.raises(ConfigError, match="keep_static_boxes=true"):
        GeometricConfig(enabled=True, flag_points=False)
    assert not GeometricConfig(enabled=True, flag_points=False, keep_static_boxes=True).flag_points
