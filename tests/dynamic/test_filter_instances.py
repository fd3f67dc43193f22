"""Instance masks in SLAM (``slam.dynamic.mask``): a detection with a mask drops the keypoints on its (dilated)
mask, not every keypoint in its box; without a trusted mask it falls back to the box, as ``mask=box`` always
does."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.trajectory import Trajectory
from vslam.data.types import Frame, PinholeCamera
from vslam.dynamic import DynamicConfig, DynamicFilter, dilate, in_boxes, in_mask
from vslam.dynamic.detector import Detections
from vslam.dynamic.masking import Instances, crop_mask, grow_in_box, paint
from vslam.errors import ConfigError
from vslam.eval import EvalConfig, evaluate
from vslam.features.base import Features
from vslam.tracking.slam import SlamConfig, SlamTracker

CAM = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
BOX = np.array([10.0, 8.0, 40.0, 40.0])


def _feats() -> Features:
    xs, ys = np.meshgrid(np.arange(0, 64, 2.0), np.arange(0, 48, 2.0))
    uv = np.stack([xs.ravel(), ys.ravel()], 1) + 0.3
    n = len(uv)
    return Features(uv.copy(), uv.copy(), np.zeros((n, 32), np.uint8), np.zeros(n, np.int64), np.ones(n))


def _l_mask(dx: int = 0) -> np.ndarray:
    """An L in BOX (moved ``dx`` px right): a bar down its left side and one along its bottom."""
    m = np.zeros((48, 64), bool)
    m[8:41, 10 + dx:17 + dx] = True
    m[34:41, 10 + dx:41 + dx] = True
    return m


class _Fixed:
    """A detector that finds the same person every frame, with ``masks`` ((K,H,W) or None: no mask head)."""

    def __init__(self, boxes, masks):
        self.boxes, self.masks = np.asarray(boxes, np.float64).reshape(-1, 4), masks

    def detect(self, image):
        k = len(self.boxes)
        return Detections(self.boxes, np.full(k, 0.9), np.zeros(k, np.int64), np.array(["person"] * k, dtype=object),
                          self.masks)


def _cfg(mask: str = "instance", **kw) -> DynamicConfig:
    return DynamicConfig(enabled=True, source="detector", dilation_px=2, box_memory_s=0.0, mask=mask, **kw)  # type: ignore[arg-type]


def _frame(i: int = 0, t: float = 0.0) -> Frame:
    return Frame(i, t, np.zeros((48, 64), np.uint8))


def test_instance_masks_drop_only_the_keypoints_on_the_dilated_mask():
    f, mask = _feats(), _l_mask()
    det = _Fixed([BOX], mask[None])
    inst = DynamicFilter(_cfg(), CAM, detector=det).keep(_frame(), f)
    np.testing.assert_array_equal(inst, ~in_mask(f.raw, dilate(mask, 2)))
    box = DynamicFilter(_cfg("box"), CAM, detector=det).keep(_frame(), f)
    np.testing.assert_array_equal(box, ~in_boxes(f.raw, BOX[None], 2.0))
    in_box_off_mask = in_boxes(f.raw, BOX[None]) & ~in_mask(f.raw, dilate(mask, 2))
    assert in_box_off_mask.sum() > 50 and inst[in_box_off_mask].all() and not box[in_box_off_mask].any()
    # the same detections computed ahead (the SLAM front end's prefetch thread) give the same keypoints
    objects = DynamicFilter(_cfg(), CAM, detector=det).detect(_frame())
    assert objects.masks[0] is not None and objects.masks[0].pixels.shape == (33, 31)
    np.testing.assert_array_equal(DynamicFilter(_cfg(), CAM, detector=object()).keep(_frame(), f, objects), inst)
    assert pickle.loads(pickle.dumps(objects)).masks[0].x0 == 10  # it travels from the front-end process
    assert DynamicFilter(_cfg("box"), CAM, detector=det).detect(_frame()).masks == (None,)


def test_a_detection_without_a_trusted_mask_masks_its_box():
    """No mask head (masks None), an empty mask, one covering less than mask_min_fill of its box: the box."""
    f = _feats()
    box_keep = ~in_boxes(f.raw, BOX[None], 2.0)
    speck = np.zeros((1, 48, 64), bool)
    speck[0, 20:23, 20:23] = True  # 9 of the box's 31 x 33 pixels
    for masks in (None, np.zeros((1, 48, 64), bool), speck):
        np.testing.assert_array_equal(DynamicFilter(_cfg(), CAM, detector=_Fixed([BOX], masks)).keep(_frame(), f), box_keep)
    # a mask trusted at a lower mask_min_fill
    loose = DynamicFilter(_cfg(mask_min_fill=0.005), CAM, detector=_Fixed([BOX], speck)).keep(_frame(), f)
    np.testing.assert_array_equal(loose, ~in_mask(f.raw, dilate(speck[0], 2)))
    # a mask never reaches past its box (plus dilation_px)
    spill = np.ones((1, 48, 64), bool)
    np.testing.assert_array_equal(DynamicFilter(_cfg(), CAM, detector=_Fixed([BOX], spill)).keep(_frame(), f),
                                  ~in_mask(f.raw, dilate(paint([crop_mask(spill[0], BOX, 0.2)], (48, 64)), 2)))
    assert crop_mask(spill[0], np.array([70.0, 0, 80, 10]), 0.2) is None  # a box outside the image


def test_box_memory_unions_the_remembered_masks():
    """A person whose L moves 8 px right per frame, found at t = 0 and 0.1 s, missed at 0.2 s: with box_memory_s
    0.15 s frame 1 masks both Ls (not the rest of the boxes), frame 2 the second L only (every box held:
    box_memory_min_hits 1)."""

    class Walk:
        def __init__(self):
            self.n = 0

        def detect(self, image):
            k, self.n = self.n, self.n + 1
            if k >= 2:
                return Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64), np.array([], dtype=object),
                                  np.zeros((0, 48, 64), bool))
            return Detections((BOX + [8 * k, 0, 8 * k, 0])[None], np.array([0.9]), np.array([0]),
                              np.array(["person"], dtype=object), _l_mask(8 * k)[None])

    f = _feats()
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=2, box_memory_s=0.15, box_track_s=0.0,
                        box_memory_min_hits=1)
    flt = DynamicFilter(cfg, CAM, detector=Walk())
    kept = [flt.keep(_frame(i, 0.1 * i), f) for i in range(3)]
    a, b = in_mask(f.raw, dilate(_l_mask(0), 2)), in_mask(f.raw, dilate(_l_mask(8), 2))
    np.testing.assert_array_equal(kept[0], ~a)
    np.testing.assert_array_equal(kept[1], ~(a | b))
    np.testing.assert_array_equal(kept[2], ~b)
    assert (kept[1] & in_boxes(f.raw, np.array([[10.0, 8, 48, 40]]))).sum() > 30  # between and beside the Ls


def test_box_memory_holds_only_objects_seen_twice():
    """box_memory_min_hits 2: a detection of one frame only (a false box) is masked in its own frame and not
    held after it; an object found in two frames is held when the detector then misses it."""

    class Blink:
        """A box at frames 0 (once, then gone) and, elsewhere, at frames 2 and 3; nothing from frame 4 on."""

        def __init__(self):
            self.n = 0

        def detect(self, image):
            k, self.n = self.n, self.n + 1
            boxes = {0: [[2.0, 2, 20, 20]], 2: [[40.0, 20, 60, 44]], 3: [[41.0, 20, 61, 44]]}.get(k, [])
            n = len(boxes)
            return Detections(np.array(boxes).reshape(-1, 4), np.full(n, 0.9), np.zeros(n, np.int64),
                              np.array(["person"] * n, dtype=object), None)

    f = _feats()
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=0, mask="box", box_memory_s=0.25,
                        box_track_s=0.0, box_memory_min_hits=2)
    flt = DynamicFilter(cfg, CAM, detector=Blink())
    kept = [flt.keep(_frame(i, 0.1 * i), f) for i in range(5)]
    once = in_boxes(f.raw, np.array([[2.0, 2, 20, 20]]))
    twice = in_boxes(f.raw, np.array([[41.0, 20, 61, 44]]))
    assert once.sum() > 5 and twice.sum() > 5
    np.testing.assert_array_equal(kept[0], ~once)  # its own frame masks it
    assert kept[1].all()  # seen once: not held
    np.testing.assert_array_equal(kept[4], ~twice)  # seen at frames 2 and 3: held at 4, where it is missed


def test_a_static_verdict_unmasks_the_instance():
    """``geometric.keep_static_boxes``: a box judged static in the last checked frame unmasks the overlapping
    detection of this one, its mask as well as its box."""
    f = _feats()
    flt = DynamicFilter(_cfg(), CAM, detector=_Fixed([BOX], _l_mask()[None]))
    flt._static = (BOX + 1.0)[None]  # the verdict of the previous frame (IoU > 0.5 with this frame's box)
    assert flt.keep(_frame(), f).all()


def test_ensembles_union_masks_and_boxes():
    """extra_weights: each network's detection masks what it would alone; a network without a mask head adds its
    box."""
    f = _feats()
    other = np.zeros((48, 64), bool)
    other[10:30, 45:60] = True
    first = _Fixed([BOX], _l_mask()[None])
    both = DynamicFilter(_cfg(), CAM, detector=first, extra=[_Fixed([[45.0, 10, 59, 29]], other[None])]).keep(_frame(), f)
    np.testing.assert_array_equal(both, ~in_mask(f.raw, dilate(_l_mask() | other, 2)))
    boxed = DynamicFilter(_cfg(), CAM, detector=first, extra=[_Fixed([BOX], None)]).keep(_frame(), f)
    np.testing.assert_array_equal(boxed, ~(in_boxes(f.raw, BOX[None], 2.0) | in_mask(f.raw, dilate(_l_mask(), 2))))


def test_segments_off_the_instance_are_kept():
    """keep_segments: a segment inside the box but beside the L (background the box holds) is kept with
    mask=instance and dropped with mask=box; one along the L's bar goes either way."""
    segs = np.array([[25.0, 12.0, 38.0, 28.0],  # in the box, off the L
                     [13.0, 10.0, 13.0, 38.0]])  # on the L's bar
    out = {}
    for mode in ("instance", "box"):
        flt = DynamicFilter(_cfg(mode), CAM, detector=_Fixed([BOX], _l_mask()[None]))
        flt.keep(_frame(), _feats())
        out[mode] = flt.keep_segments(_frame(), segs, segs).tolist()
    assert out == {"instance": [True, False], "box": [False, False]}


def test_masks_grow_by_half_a_prototype_cell_inside_their_box():
    """A detector whose prototype cell spans 6 image pixels: its L grows by 3 px (mask_grow_cells 0.5), within the
    box, before dilation_px."""
    f, mask = _feats(), _l_mask()

    class Coarse(_Fixed):
        def detect(self, image):
            d = super().detect(image)
            return Detections(d.boxes, d.scores, d.class_ids, d.class_names, d.masks, 6.0)

    got = DynamicFilter(_cfg(), CAM, detector=Coarse([BOX], mask[None])).keep(_frame(), f)
    grown = paint([crop_mask(dilate(mask, 3), BOX, 0.2)], (48, 64))
    np.testing.assert_array_equal(got, ~in_mask(f.raw, dilate(grown, 2)))
    assert (~got).sum() > (~DynamicFilter(_cfg(mask_grow_cells=0.0), CAM, detector=Coarse([BOX], mask[None])).keep(
        _frame(), f)).sum()
    np.testing.assert_array_equal(grow_in_box(mask, BOX, 3)[:, 45:], False)  # nothing computed past box + 3 px
    assert grow_in_box(mask, BOX, 0) is mask


def test_mask_config_is_validated():
    with pytest.raises(ConfigError, match="slam.dynamic.mask must be instance or box"):
        DynamicConfig(mask="polygon")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="mask_min_fill"):
        DynamicConfig(mask_min_fill=1.5)
    with pytest.raises(ConfigError, match="mask_grow_cells"):
        DynamicConfig(mask_grow_cells=-1)
    assert DynamicConfig().mask == "instance"
    assert len(Instances.concat([])) == 0


# -- SLAM on the synthetic dynamic room -------------------------------------------------------------------------


class _Oracle:
    """The generator's exact boxes, each with the dynamic mask within it as its instance mask (a perfect mask
    head), found by the frame's image."""

    def __init__(self, frames: list[Frame]):
        self.frames = {id(fr.image): fr for fr in frames}

    def detect(self, image):
        fr = self.frames[id(image)]
        k = len(fr.boxes)
        masks = np.zeros((k, *fr.dynamic_mask.shape), bool)
        for j, (x1, y1, x2, y2) in enumerate(fr.boxes.astype(int)):
            masks[j, y1:y2 + 1, x1:x2 + 1] = fr.dynamic_mask[y1:y2 + 1, x1:x2 + 1]
        return Detections(fr.boxes.astype(np.float64), np.ones(k), np.zeros(k, np.int64),
                          np.array(["person"] * k, dtype=object), masks)


def test_slam_with_instance_masks_keeps_more_static_keypoints_at_box_accuracy():
    """40 frames of the synthetic room (seed 1, frames 130-169: three people-sized movers, their boxes over 20-40 %
    of the view) with a perfect detector: instance masks keep static keypoints the boxes hold beside the movers,
    no mover keypoint gets through either way, and the ATE matches box masking, far below the unfiltered run's.
    The movers are cuboids whose masks fill ~90 % of their boxes, so the gain is small here (a walking person
    fills about half of its box)."""
    seq = SyntheticSequence(SyntheticConfig(n_frames=170, width=320, height=240, fx=262.5, fy=262.5, n_movers=3, seed=1))
    frames = [seq.frame(i) for i in range(130, 170)]
    gt = Trajectory(np.array([fr.timestamp for fr in frames]), np.array([fr.T_world_cam for fr in frames]))

    def run(mask: str | None) -> tuple[int, int, float]:
        st = SlamTracker(seq.calibration, "rgbd", SlamConfig())
        if mask is not None:
            cfg = DynamicConfig(enabled=True, source="detector", mask=mask)  # type: ignore[arg-type]
            st = SlamTracker(seq.calibration, "rgbd", SlamConfig(dynamic=cfg), detector=_Oracle(frames))
        poses, static, mover = [], 0, 0
        for fr in frames:
            est = st.track(fr)
            assert est.tracked
            poses.append(est.T_world_cam)
            raw = st.view.front.feats.raw
            on = in_mask(raw if st.view.kept is None else raw[st.view.kept], fr.dynamic_mask)
            static, mover = static + int((~on).sum()), mover + int(on.sum())
        ate = evaluate(Trajectory(gt.timestamps.copy(), np.array(poses)), gt, EvalConfig(align="se3")).ate
        return static, mover, ate.translation.rmse

    (s_inst, m_inst, ate_inst), (s_box, m_box, ate_box), (s_all, m_all, ate_all) = run("instance"), run("box"), run(None)
    assert m_inst == m_box == 0 and m_all > 1000
    assert s_inst > s_box + 1000  # of ~54000 static keypoints
    assert (s_all - s_inst) < 0.85 * (s_all - s_box)  # a quarter fewer static keypoints lost
    assert ate_inst <= ate_box + 0.001 and ate_inst < 0.5 * ate_all


def test_filter_takes_a_registry_checkpoint_with_its_input_settings():
    """slam.dynamic.weights naming the shipped YOLOX checkpoint (the registry's format): the filter runs it at
    img_size / wide as configured and masks its person boxes (boxes: the network has no mask head)."""
    from pathlib import Path

    import cv2

    from vslam.dynamic.yolox_detector import YoloxDetector
    from vslam.paths import data_root

    photo = data_root() / "penn_fudan/PennFudanPed/JPEGImages/FudanPed00001.jpg"
    model = Path(__file__).resolve().parents[2] / "vslam" / "models" / "yolox_nano_slam.pt"
    if not photo.is_file() or not model.is_file():
        pytest.skip(f"needs {photo} (set VSLAM_DATA) and the shipped {model.name}")
    image = cv2.imread(str(photo))
    cam = PinholeCamera(image.shape[1], image.shape[0], 500.0, 500.0, image.shape[1] / 2, image.shape[0] / 2)
    cfg = DynamicConfig(enabled=True, source="detector", weights=str(model), img_size=576, wide=True, device="cpu")
    f = DynamicFilter(cfg, cam)
    assert isinstance(f.detector, YoloxDetector) and f.detector.img_size == 576 and f.detector.wide
    assert f.detector.input_size(image.shape[:2]) == (576, 576)  # 559x536 -> 576 wide, 552.3 -> 576 high
    objs = f.detect(Frame(0, 0.0, image))
    assert len(objs.boxes) == 2 and all(m is None for m in objs.masks)  # the two pedestrians, as boxes


def test_a_static_verdict_holds_for_the_box_the_memory_holds():
    """A box judged static in frame 0 and not detected in frame 1 is still held by the box memory there: its
    verdict is held as long (it was masked again, so YOLOX-nano's intermittent person box over TUM's teddy bear
    blanked the scene's main texture between the frames that found it)."""
    from vslam.dynamic import GeometricConfig

    f = _feats()
    boxes = [BOX]

    class Once(_Fixed):
        def detect(self, image):
            d = super().detect(image)
            out = Detections(np.array(boxes).reshape(-1, 4), d.scores[: len(boxes)], d.class_ids[: len(boxes)],
                             d.class_names[: len(boxes)])
            boxes.clear()  # found in the first frame only
            return out

    geo = GeometricConfig(enabled=True, keep_static_boxes=True)
    cfg = DynamicConfig(enabled=True, source="detector", dilation_px=2, box_memory_s=0.1, mask="box", geometric=geo)
    flt = DynamicFilter(cfg, CAM, detector=Once([BOX], None))
    verdicts = iter([BOX[None], np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 4))])
    flt._static_boxes = lambda feats, g: next(verdicts)  # the check's verdicts: static in frame 0, no box later
    kept = []
    for i, t in enumerate((0.0, 0.033, 0.066, 0.2)):
        kept.append(flt.keep(_frame(i, t), f))
        flt.observe(np.eye(4))
    inside = in_boxes(f.raw, BOX[None], 2.0)
    assert inside.sum() > 5
    np.testing.assert_array_equal(kept[0], ~inside)  # its own frame masks it: the verdict comes after tracking
    assert kept[1].all() and kept[2].all()  # held by the memory, and so is its verdict
    assert kept[3].all()  # both gone after box_memory_s
