"""What one frame's images alone determine: keypoints (and the right image's), line segments, keypoint depth,
the detector's dynamic objects. No map state is read, so the pipeline computes it ahead, on a thread or in a
child process (``vslam.tracking.frontend_process``), while the previous frame is tracked."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from vslam.backend.ba import StereoCamera
from vslam.data.types import Calibration, Frame, SensorKind
from vslam.dynamic.masking import Instances
from vslam.features import Features
from vslam.features.depth import depth_rgbd, depth_stereo
from vslam.features.lines import LineFeatures
from vslam.features.stereo import depth_stereo_rectified, is_rectified


@dataclass
class FrontEnd:
    """One frame's image-only results: keypoints, the right image's keypoints (stereo), line segments (lines on),
    keypoint depth (None: computed in ``track``, after dynamic filtering), the detector's boxes and instance
    masks of dynamic objects (``slam.dynamic.source=detector``, ``DynamicFilter.detect``), and ms per stage
    where it ran."""

    feats: Features
    right: Features | None
    lines: LineFeatures | None
    depth: np.ndarray | None
    ms: dict[str, float]
    objects: Instances | None = None


@dataclass
class FrameView:
    """What the last ``track`` call saw, for viewers (``vslam.viz``): references, never copied, never read back
    by tracking. ``front``: the frame's ``FrontEnd`` (all keypoints, segments, detector boxes); ``kept`` (M,)
    indices of the keypoints dynamic filtering let through (None: all); ``point_ids`` (M,) map point matched per
    kept keypoint, -1 none (None: not tracked against a map, e.g. the map's first frame); ``moving`` (M,) bool,
    flagged by the geometric motion check (None: no check)."""

    front: FrontEnd
    kept: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    moving: np.ndarray | None = None


def sensor_rig(calib: Calibration, sensor: SensorKind, cfg: Any) -> tuple[float, bool, StereoCamera]:
    """(baseline, rectified, the camera of BA's stereo factors) of a rig: a stereo pair's baseline, RGB-D's virtual
    one (``backend.rgbd_virtual_baseline``: depth enters BA as a disparity), 0 for monocular. ``cfg``: a
    ``SlamConfig``."""
    if sensor == "stereo":
        if calib.cam1 is None or calib.baseline is None:
            raise ValueError("stereo SLAM needs cam1 and its extrinsics in the calibration")
        baseline = float(calib.baseline)
    elif sensor == "rgbd":
        baseline = cfg.backend.rgbd_virtual_baseline
    else:
        baseline = 0.0
    # the disparity's own noise where it is measured apart from the keypoint: a depth sensor, or the sub-pixel
    # stereo refinement of a rectified rig (``vslam.features.stereo``)
    rectified = sensor == "stereo" and cfg.tracking.stereo_refine and is_rectified(calib)
    disparity_sigma = 0.0
    if sensor == "rgbd":
        disparity_sigma = cfg.backend.rgbd_disparity_sigma
    elif rectified:
        disparity_sigma = cfg.backend.stereo_disparity_sigma
    cam = calib.cam0
    return baseline, rectified, StereoCamera(cam.fx, cam.fy, cam.cx, cam.cy, baseline, disparity_sigma)


class FrontEndMaker:
    """``make(frame) -> FrontEnd``. ``lines``: the line stage (segments; on its own thread when it has one),
    ``dynamic``: the dynamic filter (its detector; keypoint depth then waits until the filter has run, because
    rectified stereo matching depends on which keypoints are left)."""

    def __init__(self, extractor: Any, calib: Calibration, sensor: SensorKind, cfg: Any, rectified: bool,
                 lines: Any = None, dynamic: Any = None):
        self.extractor, self.calib, self.sensor, self.cfg = extractor, calib, sensor, cfg
        self.cam, self.rectified, self.lines, self.dynamic = calib.cam0, rectified, lines, dynamic

    def extract(self, frame: Frame) -> tuple[Features, Features | None]:
        """Keypoints of the image and (stereo) of the right image: one batch when the extractor has
        ``detect_many`` (a network: one forward pass for the pair)."""
        right_img = frame.right if self.sensor == "stereo" else None
        if right_img is not None and hasattr(self.extractor, "detect_many") and right_img.shape == frame.image.shape:
            left, right = self.extractor.detect_many([frame.image, right_img], [self.cam, self.calib.cam1])
            return left, right
        feats = self.extractor.detect(frame.image, self.cam)
        if right_img is None or not len(feats):
            return feats, None
        return feats, self.extractor.detect(right_img, self.calib.cam1)  # type: ignore[arg-type]

    def depth(self, frame: Frame, feats: Features, right: Features | None) -> np.ndarray:
        tc = self.cfg.tracking
        if self.sensor == "rgbd":
            return depth_rgbd(frame.depth, feats, tc.min_depth, tc.max_depth)
        if self.sensor == "stereo" and right is not None and len(feats):
            if self.rectified:
                return depth_stereo_rectified(frame.image, frame.right, feats, right, self.calib, tc.min_depth,
                                              tc.max_depth, n_levels=self.cfg.features.n_levels)
            return depth_stereo(feats, right, self.calib, tc.min_depth, tc.max_depth, tc.stereo_max_px)
        return np.full(len(feats), np.nan)

    def make(self, frame: Frame) -> FrontEnd:
        t0 = time.perf_counter()
        pending = self.lines.submit(frame) if self.lines is not None else None
        feats, right = self.extract(frame)
        t1 = time.perf_counter()
        lines = self.lines.detect(frame) if self.lines is not None and pending is None else None
        t2 = time.perf_counter()
        depth = self.depth(frame, feats, right) if self.dynamic is None else None
        t3 = time.perf_counter()
        objects = self.dynamic.detect(frame) if self.dynamic is not None else None
        t4 = time.perf_counter()
        if pending is not None:  # beside the networks, "lines" is what was left to wait for after them
            lines = pending.result()
        t5 = time.perf_counter()
        ms = {"features": (t1 - t0) * 1e3, "lines": (t2 - t1 + t5 - t4) * 1e3, "depth": (t3 - t2) * 1e3,
              "detector": (t4 - t3) * 1e3}
        return FrontEnd(feats, right, lines, depth, ms, objects)
