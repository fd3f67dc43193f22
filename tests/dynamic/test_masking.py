"""Mask application: exactly the keypoints on masks / boxes are dropped, before tracking and before mapping."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.types import Frame, PinholeCamera
from vslam.dynamic import DynamicConfig, DynamicFilter, dilate, in_boxes, in_mask
from vslam.errors import ConfigError
from vslam.features.base import Features
from vslam.tracking.slam import SlamConfig, SlamTracker

CAM = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)


def _feats(uv: np.ndarray) -> Features:
    n = len(uv)
    return Features(uv.copy(), uv.copy(), np.zeros((n, 32), np.uint8), np.zeros(n, np.int64), np.ones(n))


def _grid_feats() -> Features:
    xs, ys = np.meshgrid(np.arange(0, 64, 3.0), np.arange(0, 48, 3.0))
    return _feats(np.stack([xs.ravel(), ys.ravel()], 1) + 0.3)


def test_in_mask_and_boxes_are_exact():
    f = _grid_feats()
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:40] = True  # rows 10..19, cols 30..39
    u, v = np.rint(f.raw[:, 0]), np.rint(f.raw[:, 1])
    expect = (u >= 30) & (u <= 39) & (v >= 10) & (v <= 19)
    assert expect.sum() > 5
    np.testing.assert_array_equal(in_mask(f.raw, mask), expect)
    # a box covers its closed pixel rectangle; pad grows it on every side
    box = np.array([[30.0, 10.0, 39.0, 19.0]])
    x, y = f.raw[:, 0], f.raw[:, 1]
    np.testing.assert_array_equal(in_boxes(f.raw, box), (x >= 30) & (x <= 39) & (y >= 10) & (y <= 19))
    np.testing.assert_array_equal(in_boxes(f.raw, box, 2.0), (x >= 28) & (x <= 41) & (y >= 8) & (y <= 21))
    # grow by 20 % of the 9 x 9 box on each side (1.8 px), plus 2 px
    np.testing.assert_array_equal(in_boxes(f.raw, box, 2.0, 0.2), (x >= 26.2) & (x <= 42.8) & (y >= 6.2) & (y <= 22.8))
    assert not in_boxes(f.raw, np.zeros((0, 4))).any()
    # keypoints outside the image are not masked (no wrap-around indexing)
    assert not in_mask(np.array([[-1.0, 5.0], [64.2, 5.0], [5.0, 48.0]]), np.ones((48, 64), bool)).any()
    assert dilate(mask, 2).sum() == 14 * 14


def test_filter_keeps_exactly_the_unmasked_keypoints():
    f = _grid_feats()
    mask = np.zeros((48, 64), bool)
    mask[5:30, 2:20] = True
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8), dynamic_mask=mask)
    keep = DynamicFilter(DynamicConfig(enabled=True, source="gt_mask", dilation_px=0), CAM).keep(frame, f)
    np.testing.assert_array_equal(keep, ~in_mask(f.raw, mask))
    # dilation: the keypoints within dilation_px of the mask go too
    keep3 = DynamicFilter(DynamicConfig(enabled=True, source="gt_mask", dilation_px=3), CAM).keep(frame, f)
    np.testing.assert_array_equal(keep3, ~in_mask(f.raw, dilate(mask, 3)))
    assert keep3.sum() < keep.sum()
    # boxes only (no pixel mask): the boxes are used
    fb = Frame(0, 0.0, np.zeros((48, 64), np.uint8), boxes=np.array([[2.0, 5.0, 19.0, 29.0]]))
    keepb = DynamicFilter(DynamicConfig(enabled=True, source="gt_mask", dilation_px=0), CAM).keep(fb, f)
    np.testing.assert_array_equal(keepb, keep)
    # source none keeps everything
    assert DynamicFilter(DynamicConfig(enabled=True, source="none"), CAM).keep(frame, f).all()


def test_config_errors():
    with pytest.raises(ConfigError):
        DynamicConfig(source="yolo")  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        DynamicFilter(DynamicConfig(enabled=True, source="detector", weights="no/such/detector.pt"), CAM)


def test_slam_never_tracks_or_maps_masked_keypoints():
    """A fixed mask over the left third of a static synthetic room: no keyframe keypoint (the mapping input) and no
    map point observation lies under it, and with the filter off the same frames do use that region."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=12, width=320, height=240, fx=262.5, fy=262.5, n_movers=0))
    mask = np.zeros((240, 320), bool)
    mask[:, :110] = True
    frames = [dataclasses.replace(fr, dynamic_mask=mask) for fr in seq]

    def run(enabled: bool) -> SlamTracker:
        cfg = SlamConfig(dynamic=DynamicConfig(enabled=enabled, source="gt_mask", dilation_px=0))
        st = SlamTracker(seq.calibration, "rgbd", cfg)
        for fr in frames:
            assert st.track(fr).tracked
        return st

    on, off = run(True), run(False)
    for st, expect_masked in ((on, False), (off, True)):
        raw = np.concatenate([kf.features.raw for kf in st.map.keyframes.values()])
        assert in_mask(raw, mask).any() == expect_masked
        obs = [st.map.keyframes[k].features.raw[i] for p in st.map.points.values() for k, i in p.observations.items()]
        assert in_mask(np.array(obs), mask).any() == expect_masked


def _masked_fraction(raw: np.ndarray, mask: np.ndarray) -> np.ndarray:
    t = np.linspace(0.0, 1.0, 9)[None, :, None]
    pts = raw[:, None, :2] * (1.0 - t) + raw[:, None, 2:] * t
    return in_mask(pts.reshape(-1, 2), mask).reshape(len(raw), -1).mean(axis=1)


def test_segments_on_dynamic_objects_are_dropped():
    """A segment goes when all nine of its samples are masked (it lies on the object): inside -> dropped, outside
    -> kept, partly inside (a static edge ending at the person, or crossing the background of a loose box) ->
    kept; one sample pixel outside the mask is enough to keep it."""
    mask = np.zeros((48, 64), bool)
    mask[10:30, 20:40] = True  # cols 20..39
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8), dynamic_mask=mask)
    filt = DynamicFilter(DynamicConfig(enabled=True, source="gt_mask", dilation_px=0), CAM)
    filt.keep(frame, _grid_feats())
    segs = np.array([[22.0, 12.0, 37.0, 27.0],   # inside
                     [2.0, 2.0, 60.0, 5.0],      # outside
                     [0.0, 20.0, 24.0, 20.0],    # samples at x = 0, 3, ..., 24: 21 and 24 inside (2 of 9)
                     [0.0, 20.0, 64.0, 20.0],    # x = 0, 8, ..., 64: 24, 32 inside (2 of 9) -> kept
                     [12.0, 20.0, 36.0, 20.0],   # x = 12, 15, ..., 36: 21..36 inside (6 of 9) -> kept
                     [20.0, 12.0, 39.0, 29.0],   # the mask's diagonal, end points on its last pixels -> dropped
                     [20.0, 12.0, 40.0, 29.0]])  # ... one column further: the end sample is outside -> kept
    frac = _masked_fraction(segs, mask)
    np.testing.assert_allclose(frac, [1.0, 0.0, 2 / 9, 2 / 9, 6 / 9, 1.0, 8 / 9])
    np.testing.assert_array_equal(filt.keep_segments(frame, segs, segs), [False, True, True, True, True, False, True])
    assert filt.keep_segments(frame, np.zeros((0, 4)), np.zeros((0, 4))).shape == (0,)


def test_slam_never_tracks_or_maps_masked_segments():
    """With lines on, the segments a frame hands to line tracking and mapping are the unmasked ones; with the
    filter off the same frames do use segments under the mask."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=6, width=320, height=240, fx=262.5, fy=262.5, n_movers=0))
    mask = np.zeros((240, 320), bool)
    mask[:, :110] = True
    frames = [dataclasses.replace(fr, dynamic_mask=mask) for fr in seq]
    for enabled in (True, False):
        cfg = SlamConfig(dynamic=DynamicConfig(enabled=enabled, source="gt_mask", dilation_px=0),
                         lines=dataclasses.replace(SlamConfig().lines, enabled=True))
        st = SlamTracker(seq.calibration, "rgbd", cfg)
        worst = 0.0
        for fr in frames:
            assert st.track(fr).tracked
            assert len(st._stage("lines").feats) > 5
            worst = max(worst, float(_masked_fraction(st._stage("lines").feats.raw, mask).max()))
        assert (worst < 1.0) == enabled


def test_detector_source_masks_only_confident_boxes_of_listed_classes():
    from vslam.dynamic.detector import Detections

    class FakeDetector:
        def detect(self, image):
            return Detections(np.array([[2.0, 5.0, 19.0, 29.0], [40.0, 5.0, 60.0, 40.0], [25.0, 30.0, 35.0, 45.0]]),
                              np.array([0.9, 0.9, 0.2]), np.array([0, 1, 0]), np.array(["person", "tv", "person"], dtype=object))

    f = _grid_feats()
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=0, score_threshold=0.35)
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8))
    keep = DynamicFilter(cfg, CAM, detector=FakeDetector()).keep(frame, f)
    np.testing.assert_array_equal(keep, ~in_boxes(f.raw, np.array([[2.0, 5.0, 19.0, 29.0]])))
    # detected ahead (the SLAM front end's prefetch thread): the same boxes, and keep() runs no network
    objects = DynamicFilter(cfg, CAM, detector=FakeDetector()).detect(frame)
    np.testing.assert_array_equal(objects.boxes, [[2.0, 5.0, 19.0, 29.0]])
    assert objects.masks == (None,)  # no mask head: the box is masked
    np.testing.assert_array_equal(DynamicFilter(cfg, CAM, detector=object()).keep(frame, f, objects), keep)
    assert DynamicFilter(DynamicConfig(enabled=True, source="gt_mask"), CAM).detect(frame) is None


def test_keypoints_on_depth_edges_are_not_checked():
    """geometric.edge_m: a keypoint whose 5x5 depth neighbourhood spans a jump (an outline: one pixel off reads
    the background) gets no depth, so the check can neither flag it nor compare it; a hole nearby is no edge
    (Kinect depth has holes everywhere); off by default."""
    from vslam.data.types import Frame
    from vslam.dynamic import GeometricConfig
    from vslam.features.base import Features

    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 32:] = 3.0  # a depth edge at x = 31.5
    depth[5:8, 5:8] = 0.0  # a hole
    uv = np.array([[10.0, 20.0], [31.0, 20.0], [33.0, 20.0], [50.0, 20.0], [6.0, 9.0]])
    f = Features(uv, uv, np.zeros((5, 32), np.uint8), np.zeros(5), np.zeros(5))
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8), depth=depth)
    on = DynamicFilter(DynamicConfig(enabled=True, source="none", geometric=GeometricConfig(enabled=True, edge_m=0.05)), CAM)
    z = on._check_depth(frame, f.raw)
    np.testing.assert_array_equal(np.isnan(z), [False, True, True, False, False])
    np.testing.assert_allclose(z[[0, 3, 4]], [2.0, 3.0, 2.0])
    off = DynamicFilter(DynamicConfig(enabled=True, source="none", geometric=GeometricConfig(enabled=True)), CAM)
    np.testing.assert_allclose(off._check_depth(frame, f.raw)[:4], [2.0, 2.0, 3.0, 3.0])


class _Blink:
    """A detector that finds one person box in the first frame only."""

    def __init__(self, box):
        self.box, self.calls = np.asarray(box, dtype=np.float64).reshape(1, 4), 0

    def detect(self, image):
        from vslam.dynamic.detector import Detections

        self.calls += 1
        if self.calls == 1:
            return Detections(self.box, np.array([0.9]), np.array([0]), np.array(["person"], dtype=object))
        return Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), np.array([], dtype=object))


def test_detector_boxes_are_remembered_for_box_memory_s():
    """A person found at t = 0 and missed at t = 0.1 s is still masked then (box_memory_s = 0.15), not at 0.2 s
    (every detection held: box_memory_min_hits 1)."""
    uv = np.array([[10.0, 10.0], [40.0, 10.0]])
    f = Features(uv, uv, np.zeros((2, 32), np.uint8), np.zeros(2), np.zeros(2))
    flt = DynamicFilter(DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.15, box_track_s=0.0,
                                      box_memory_min_hits=1),
                        CAM, detector=_Blink([0.0, 0, 20, 20]))
    kept = [flt.keep(Frame(i, t, np.zeros((48, 64), np.uint8)), f).tolist() for i, t in enumerate((0.0, 0.1, 0.2))]
    assert kept == [[False, True], [False, True], [True, True]]
    none = DynamicFilter(DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.0, box_track_s=0.0),
                         CAM, detector=_Blink([0.0, 0, 20, 20]))
    assert [none.keep(Frame(i, t, np.zeros((48, 64), np.uint8)), f).tolist() for i, t in enumerate((0.0, 0.1))] == [[False, True], [True, True]]


def test_detect_every_runs_the_detector_on_every_nth_frame_and_holds_its_boxes_between():
    """detect_every = 3: the network sees frames 0, 3, 6 only; frames 1-2 and 4-5 mask the last detection's boxes
    even without box memory, and the prefetch thread's ``detect`` gives None for them (nothing to carry)."""
    from vslam.dynamic.detector import Detections

    class Walker:  # a person box that moves 20 px right per call
        def __init__(self):
            self.images: list[int] = []

        def detect(self, image):
            self.images.append(int(image[0, 0]))
            x = 20.0 * (len(self.images) - 1)
            return Detections(np.array([[x, 0.0, x + 10.0, 20.0]]), np.array([0.9]), np.array([0]), np.array(["person"], dtype=object))

    uv = np.array([[5.0, 10.0], [25.0, 10.0], [45.0, 10.0]])
    f = Features(uv, uv, np.zeros((3, 32), np.uint8), np.zeros(3), np.zeros(3))
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.0, box_track_s=0.0, detect_every=3)
    det = Walker()
    flt = DynamicFilter(cfg, CAM, detector=det)
    frames = [Frame(i, 0.1 * i, np.full((48, 64), i, np.uint8)) for i in range(7)]
    kept = [flt.keep(fr, f).tolist() for fr in frames]
    assert det.images == [0, 3, 6]
    assert kept == [[False, True, True]] * 3 + [[True, False, True]] * 3 + [[True, True, False]]
    ahead = DynamicFilter(cfg, CAM, detector=Walker())
    assert [ahead.detect(fr) is None for fr in frames] == [False, True, True, False, True, True, False]
    with pytest.raises(ConfigError, match="detect_every"):
        DynamicConfig(detect_every=0)


def test_segment_samples_read_depth_as_keypoints_do():
    """keep_segments reads its samples' depth by the keypoints' rules: with geometric.edge_m a segment running
    along a depth edge (a walker's outline) has no depth there, so next to a flagged mover it is masked whatever
    the pixel reads; without edge_m its samples read the background 1 m behind the mover and it stays."""
    from vslam.dynamic import GeometricConfig

    depth = np.full((48, 64), 2.0, np.float32)
    depth[:, 32:] = 3.0  # the mover at 2 m on the left, background at 3 m
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8), depth=depth)
    seg = np.array([[32.0, 10.0, 32.0, 30.0]])  # along the edge, on its background side
    kept = []
    for edge_m in (0.05, 0.0):
        geo = GeometricConfig(enabled=True, edge_m=edge_m)
        filt = DynamicFilter(DynamicConfig(enabled=True, source="none", geometric=geo), CAM)
        filt.keep(frame, _grid_feats())
        filt.geo._region_uv, filt.geo._region_z = np.array([[28.0, 20.0]]), np.array([2.0])  # flagged last frame
        kept.append(bool(filt.keep_segments(frame, seg, seg)[0]))
    assert kept == [False, True]


def test_extra_detectors_boxes_are_unioned_with_the_first_ones():
    """extra_weights (an ensemble): a keypoint is masked when any network boxes it; each network keeps its own
    score threshold test and class list."""
    from vslam.dynamic.detector import Detections

    class One:
        def __init__(self, box, score, name="person"):
            self.box, self.score, self.name = box, score, name

        def detect(self, image):
            return Detections(np.array([self.box]), np.array([self.score]), np.array([0]), np.array([self.name], dtype=object))

    uv = np.array([[5.0, 10.0], [25.0, 10.0], [45.0, 10.0]])
    f = Features(uv, uv, np.zeros((3, 32), np.uint8), np.zeros(3), np.zeros(3))
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.0, score_threshold=0.3)
    frame = Frame(0, 0.0, np.zeros((48, 64), np.uint8))
    first = One([0.0, 0.0, 10.0, 20.0], 0.9)
    keep = DynamicFilter(cfg, CAM, detector=first, extra=[One([20.0, 0.0, 30.0, 20.0], 0.5)]).keep(frame, f)
    assert keep.tolist() == [False, False, True]
    weak = DynamicFilter(cfg, CAM, detector=first, extra=[One([20.0, 0.0, 30.0, 20.0], 0.2)]).keep(frame, f)
    tv = DynamicFilter(cfg, CAM, detector=first, extra=[One([20.0, 0.0, 30.0, 20.0], 0.9, "tv")]).keep(frame, f)
    assert weak.tolist() == tv.tolist() == [False, True, True]


def test_extra_weights_load_one_network_each():
    from vslam.dynamic.detector import default_weights

    cfg = DynamicConfig(enabled=True, source="detector", device="cpu", extra_weights=(str(default_weights()),))
    flt = DynamicFilter(cfg, CAM)
    assert len(flt.extra) == 1 and flt.extra[0] is not flt.detector
    assert len(DynamicFilter(dataclasses.replace(cfg, source="gt_mask"), CAM).extra) == 0
    with pytest.raises(ConfigError, match=r"nope\.pt: detector weights not found \(slam\.dynamic\.extra_weights\)"):
        DynamicFilter(dataclasses.replace(cfg, extra_weights=("nope.pt",)), CAM)


def test_a_box_the_detector_loses_is_followed_by_its_keypoints_for_box_track_s():
    """A person found at t = 0 only, whose keypoints move 5 px right per frame: with box_track_s its box follows
    them (still masked at 0.3 s, a static keypoint beside it is not), without it the person leaks at once, and
    it expires after box_track_s; keypoints that match nothing leave the box where it was."""
    rng = np.random.default_rng(0)
    person = np.stack(np.meshgrid([14.0, 20.0, 26.0], [15.0, 25.0, 35.0]), -1).reshape(-1, 2)
    desc = rng.integers(0, 256, (len(person) + 1, 32), dtype=np.uint8)

    def feats(k: int, same_desc: bool = True) -> Features:
        uv = np.vstack([person + [5.0 * k, 0.0], [[8.0, 44.0]]])
        d = desc if same_desc else rng.integers(0, 256, desc.shape, dtype=np.uint8)
        return Features(uv, uv.copy(), d, np.zeros(len(uv), np.int64), np.ones(len(uv)))

    def run(track_s: float, same_desc: bool = True) -> list[list[bool]]:
        cfg = DynamicConfig(enabled=True, source="detector", dilation_px=0, box_memory_s=0.0, box_track_s=track_s)
        flt = DynamicFilter(cfg, CAM, detector=_Blink([10.0, 10, 30, 40]))
        return [flt.keep(Frame(k, 0.1 * k, np.zeros((48, 64), np.uint8)), feats(k, k == 0 or same_desc)).tolist()
                for k in range(4)]

    person_kept = lambda rows: [sum(r[:-1]) for r in rows]  # noqa: E731
    followed = run(1.0)
    assert person_kept(followed) == [0, 0, 0, 0] and all(r[-1] for r in followed)
    assert person_kept(run(0.0)) == [0, 9, 9, 9]
    assert person_kept(run(0.15)) == [0, 0, 9, 9]  # followed until 0.15 s after the last detection
    # no match inside the box: it stays at x 10-30, and the person's points that moved past x = 30 leak
    assert person_kept(run(1.0, same_desc=False)) == [0, 3, 3, 6]
