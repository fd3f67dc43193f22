"""TUM RGB-D benchmark reader (and our synthetic sequences, which share its layout).

Layout of a sequence folder (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgb.txt, depth.txt        "timestamp filename" per line, '#' comments
    rgb/<t>.png               8-bit colour, 640x480
    depth/<t>.png             16-bit, depth_scale (5000) units per metre, 0 = no reading
    groundtruth.txt           "t tx ty tz qx qy qz qw", pose of the colour camera's optical centre
    accelerometer.txt         "t ax ay az" (Kinect accelerometer, m/s^2), optional
    calibration.yaml          optional override of the intrinsics (our synthetic generator writes it)
    mask.txt + mask/<t>.png   optional, synthetic: uint8 0/255 dynamic-object masks
    boxes.txt                 optional, synthetic: "t object_id x1 y1 x2 y2" pixels

The camera and its distortion come from the folder name (freiburg1/2/3, the
values TUM publishes), unless ``calibration.yaml`` says otherwise.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from vslam.data.association import associate
from vslam.data.association import check as check_pairing
from vslam.data.association import check_depth_image, no_pairs_text
from vslam.data.association import report as pairing_report
from vslam.data.calibration import check_calibration, check_image_size, image_file_size
from vslam.data.euroc import parse_distortion_model
from vslam.data.textio import check_increasing, read_numeric, read_rows, read_yaml_mapping, require_dir, require_file
from vslam.data.trajectory import Trajectory, read_trajectory
from vslam.data.types import Calibration, Frame, PinholeCamera, SensorKind, Sequence
from vslam.errors import DatasetError

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0  # raw depth units per metre in every TUM RGB-D depth PNG

# Published colour-camera calibrations; distortion is OpenCV (k1, k2, p1, p2, k3).
TUM_CAMERAS: dict[str, PinholeCamera] = {
    "freiburg1": PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3, "radtan", (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": PinholeCamera(640, 480, 520.9, 521.0, 325.1, 249.7, "radtan", (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    # fr3 images were undistorted by the Kinect driver before recording.
    "freiburg3": PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6),
}
# ROS openni default, what TUM recommends when the camera is unknown.
ROS_DEFAULT_CAMERA = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)

CALIBRATION_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "distortion_model", "distortion", "depth_scale")


def camera_for_folder(name: str) -> PinholeCamera | None:
    """The TUM camera a folder name refers to (``freiburg3`` or ``fr3``), else None."""
    m = re.search(r"(?:freiburg|fr)([123])(?![0-9])", name.lower())
    return TUM_CAMERAS[f"freiburg{m.group(1)}"] if m else None


def read_calibration_yaml(path: Path, camera: PinholeCamera, depth_scale: float) -> tuple[PinholeCamera, float]:
    """Override ``camera`` / ``depth_scale`` with the keys of a calibration.yaml (an unknown key is an error)."""
    data, lines = read_yaml_mapping(path)
    for key in data:
        if key not in CALIBRATION_KEYS:
            raise DatasetError(path, f"unknown key {key!r}; allowed: {', '.join(CALIBRATION_KEYS)}", lines.get(str(key)))
    values: dict[str, object] = {
        "width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
    }
    for key in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale"):
        if key not in data:
            continue
        v = data[key]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v) or v <= 0:
            raise DatasetError(path, f"{key!r} must be a positive number, got {v!r}", lines.get(key))
        if key in ("width", "height") and int(v) != v:
            raise DatasetError(path, f"{key!r} must be an integer, got {v!r}", lines.get(key))
        values[key] = int(v) if key in ("width", "height") else float(v)
    scale = float(values.pop("depth_scale", depth_scale))  # type: ignore[arg-type]
    model = camera.distortion_model
    if "distortion_model" in data:
        model = parse_distortion_model(path, data["distortion_model"], lines.get("distortion_model"))
    dist: tuple[float, ...] = camera.distortion if model == camera.distortion_model else ()
    if "distortion" in data:
        d = data["distortion"]
        if not isinstance(d, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in d):
            raise DatasetError(path, f"'distortion' must be a list of numbers, got {d!r}", lines.get("distortion"))
        dist = tuple(float(x) for x in d)
    counts = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}[model]
    if len(dist) not in counts and not (model == "none" and not any(dist)):
        raise DatasetError(path, f"distortion_model {model!r} takes {' or '.join(map(str, counts))} coefficients, found {len(dist)}", lines.get("distortion"))
    cam = PinholeCamera(distortion_model=model, distortion=dist if model != "none" else (), **values)  # type: ignore[arg-type]
    return cam, scale


def read_file_list(list_path: Path, root: Path, what: str) -> tuple[np.ndarray, list[Path]]:
    """A "timestamp filename" list -> (t (N,) s, files (N,)); errors name the list and line.

    Timestamps must strictly increase and every listed file must exist.
    """
    require_file(list_path, what)
    lines, rows = read_rows(list_path, 2, numeric_cols=1)
    t = np.array([float(r[0]) for r in rows], dtype=np.float64)
    check_increasing(list_path, t, np.asarray(lines))
    files = [root / r[1] for r in rows]
    for f, ln in zip(files, lines):
        if not f.is_file():
            raise DatasetError(list_path, f"listed file {f} does not exist", ln)
    return t, files


class TumRgbdSequence(Sequence):
    """TUM RGB-D sequence folder (``rgbd_dataset_freiburgN_*``) or a synthetic one in its layout.

    path: the sequence folder.
    max_diff: seconds; rgb<->depth pairs, ground-truth poses, masks and boxes
        are matched to an rgb timestamp only within this.
    sensor: "rgbd" (every rgb image; depth from the nearest depth image within
        max_diff, else None) or "mono" (every rgb image, no depth; depth.txt not
        needed).

    Frames: image (480,640,3) uint8 BGR, depth (480,640) float32 metres (0 =
    invalid), T_world_cam from groundtruth.txt, dynamic_mask / boxes when the
    synthetic extras exist. The Kinect accelerometer is not an IMU (no gyro,
    its own clock and frame), so ``Frame.imu`` stays None and the readings
    are offered by ``accelerometer()`` instead.
    """

    def __init__(self, path: str | Path, max_diff: float = 0.02, sensor: str = "rgbd"):
        root = require_dir(Path(path), "TUM RGB-D sequence")
        if sensor not in ("rgbd", "mono"):
            raise DatasetError(root, f"sensor {sensor!r} not available for TUM RGB-D; use 'rgbd' or 'mono'")
        self.path = root
        self.name = root.name
        self.sensor = cast(SensorKind, sensor)
        self.max_diff = float(max_diff)

        t_rgb, rgb_files = read_file_list(root / "rgb.txt", root, "rgb.txt")
        if len(t_rgb) == 0:
            raise DatasetError(root / "rgb.txt", "lists no images")
        if sensor == "rgbd":
            t_depth, depth_files = read_file_list(root / "depth.txt", root, "depth.txt")
            ia, ib = associate(t_rgb, t_depth, self.max_diff)
            if len(ia) == 0:
                raise DatasetError(root / "depth.txt", no_pairs_text(
                    t_rgb, t_depth, "rgb", "depth", f"within {self.max_diff:g} s", "depth.txt")
                    + "; check the two lists' timestamps, or run with --sensor mono")
            names = [str(f.relative_to(root)) for f in rgb_files]
            self.association = pairing_report("rgb-depth", t_rgb, names, t_depth, ia, ib, self.max_diff,
                                              f"no depth image within {self.max_diff:g} s", unpaired_kept=True)
            if len(ia) < len(t_rgb):
                logger.info("%s: %d of %d rgb images have a depth image within %.3f s; the others get depth=None",
                            root, len(ia), len(t_rgb), max_diff)
            check_pairing(self.association, t_rgb, t_depth, ia, ib, root / "depth.txt", "rgb", "depth", logger)
            # Every rgb image stays a frame (a pose per input image); one without a depth partner has depth=None.
            self._depth: list[Path | None] | None = [None] * len(t_rgb)
            for i, j in zip(ia, ib):
                self._depth[i] = depth_files[j]
        else:
            self._depth = None
        self._t = t_rgb
        self._rgb = list(rgb_files)
        self.calibration = self._read_calibration(root)
        if self._depth is not None:  # depth no frame can use is refused here, not skipped frame by frame
            first = next(f for f in self._depth if f is not None)
            cam = self.calibration.cam0
            scale_from = f"depth_scale in {root / 'calibration.yaml'}" if (root / "calibration.yaml").is_file() \
                else f"TUM's {TUM_DEPTH_SCALE:g} units per metre; depth_scale in calibration.yaml otherwise"
            self.depth_median_m = check_depth_image(
                first, cv2.imread(str(first), cv2.IMREAD_UNCHANGED), (cam.width, cam.height), (np.uint16,),
                f"16-bit single-channel depth (uint16, {self.calibration.depth_scale:g} units per metre)", "rgb images",
                self.calibration.depth_scale, scale_from)

        gt_path = root / "groundtruth.txt"
        # A ground-truth problem is raised by groundtruth(), after a run has written its trajectory: it must
        # not stop SLAM, which does not need the ground truth.
        self._gt: Trajectory | None = None
        self._gt_error: DatasetError | None = None
        try:
            self._gt = read_trajectory(gt_path, "tum") if gt_path.is_file() else None
        except DatasetError as e:
            self._gt_error = e
        self._gt_idx = self._gt.nearest(self._t, self.max_diff) if self._gt is not None else np.full(len(self._t), -1)
        self._accel = self._read_accelerometer(root / "accelerometer.txt")
        self._masks = self._read_masks(root)
        self._boxes = self._read_boxes(root / "boxes.txt")

    def _read_calibration(self, root: Path) -> Calibration:
        camera = camera_for_folder(root.name)
        yaml_path = root / "calibration.yaml"
        if camera is None:
            camera = ROS_DEFAULT_CAMERA
            if not yaml_path.is_file():
                logger.warning("%s: folder name names no freiburg1/2/3 camera; using the ROS default intrinsics 525 525 319.5 239.5", root)
        scale = TUM_DEPTH_SCALE
        name = re.search(r"(?:freiburg|fr)([123])(?![0-9])", root.name.lower())
        declared = (f"the TUM freiburg{name.group(1)} camera (named by the folder; give calibration.yaml otherwise)"
                    if name else "the ROS default camera (the folder names no freiburg1/2/3; give calibration.yaml)")
        source: Path = root
        where: dict[str, tuple[str, int | None]] = {}
        if yaml_path.is_file():
            camera, scale = read_calibration_yaml(yaml_path, camera, scale)
            lines = read_yaml_mapping(yaml_path)[1]
            where = {key: (key, lines.get(key)) for key in ("fx", "fy", "cx", "cy", "width", "height", "distortion")}
            source = yaml_path
            if "width" in lines or "height" in lines:
                declared = f"{yaml_path} (width, height)"
        cal = check_calibration(Calibration(cam0=camera, depth_scale=scale if self.sensor == "rgbd" else None),
                                source, where)
        # the first image must be of the calibration's size (a later one that is not is skipped, see _load)
        check_image_size(camera, image_file_size(self._rgb[0]), self._rgb[0], declared)
        return cal

    def _read_accelerometer(self, path: Path) -> tuple[np.ndarray, np.ndarray] | None:
        if not path.is_file():
            return None
        lines, v = read_numeric(path, 4)
        check_increasing(path, v[:, 0], lines)
        return v[:, 0].copy(), v[:, 1:4].copy()

    def _read_masks(self, root: Path) -> list[Path | None] | None:
        list_path = root / "mask.txt"
        if not list_path.is_file():
            return None
        t, files = read_file_list(list_path, root, "mask.txt")
        idx = Trajectory(t, np.tile(np.eye(4), (len(t), 1, 1))).nearest(self._t, self.max_diff)
        return [files[j] if j >= 0 else None for j in idx]

    def _read_boxes(self, path: Path) -> list[np.ndarray] | None:
        """boxes.txt -> per frame (K,4) float64 x1,y1,x2,y2; (0,4) for a frame no row matches."""
        if not path.is_file():
            return None
        lines, v = read_numeric(path, 6)
        check_increasing(path, v[:, 0], lines, strict=False)
        bad = np.flatnonzero((v[:, 4] < v[:, 2]) | (v[:, 5] < v[:, 3]))
        if len(bad):
            raise DatasetError(path, "box has x2 < x1 or y2 < y1", int(lines[bad[0]]))
        t_unique, start = np.unique(v[:, 0], return_index=True)
        end = np.append(start[1:], len(v))
        idx = Trajectory(t_unique, np.tile(np.eye(4), (len(t_unique), 1, 1))).nearest(self._t, self.max_diff)
        return [v[start[j] : end[j], 2:6].copy() if j >= 0 else np.zeros((0, 4)) for j in idx]

    # -- Sequence interface ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._t)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def groundtruth(self) -> Trajectory | None:
        """groundtruth.txt at its native rate (100 Hz mocap), T_world_cam of the colour camera; DatasetError
        when the file is malformed."""
        if self._gt_error is not None:
            raise self._gt_error
        return self._gt

    # -- extras ------------------------------------------------------------------------

    def accelerometer(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(t (N,) s, accel (N,3) m/s^2) of accelerometer.txt, or None when absent."""
        return self._accel

    def frame_pose(self, i: int) -> np.ndarray | None:
        """Ground-truth T_world_cam (4,4) of frame i without decoding its images, or None."""
        j = int(self._gt_idx[i])
        return None if j < 0 or self._gt is None else self._gt.poses[j].copy()

    def frame(self, i: int) -> Frame:
        """Frame i with its images decoded; DatasetError if one does not decode."""
        frame = self._load(i)
        if frame is None:
            raise DatasetError(self._rgb[i], "frame does not decode (see the logged warning)")
        return frame

    def _load(self, i: int) -> Frame | None:
        image = cv2.imread(str(self._rgb[i]), cv2.IMREAD_COLOR)
        if image is None:
            _warn_skip(self._rgb[i], "image does not decode")
            return None
        cam = self.calibration.cam0
        if image.shape[:2] != (cam.height, cam.width):
            _warn_skip(self._rgb[i], f"image is {image.shape[1]}x{image.shape[0]}, the camera's is {cam.width}x{cam.height}")
            return None
        depth = None
        depth_path = self._depth[i] if self._depth is not None else None
        if depth_path is not None:
            raw = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
            if raw is None or raw.dtype != np.uint16 or raw.shape != image.shape[:2]:
                why = "does not decode" if raw is None else f"is {raw.dtype} {raw.shape}, expected uint16 {image.shape[:2]}"
                _warn_skip(depth_path, f"depth image {why}")
                return None
            assert self.calibration.depth_scale is not None
            depth = raw.astype(np.float32) / np.float32(self.calibration.depth_scale)
        mask = None
        mask_path = self._masks[i] if self._masks is not None else None
        if mask_path is not None:
            m = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
            if m is None or m.shape != image.shape[:2]:
                _warn_skip(mask_path, "mask does not decode" if m is None else f"mask is {m.shape}, expected {image.shape[:2]}")
                return None
            mask = m > 0
        return Frame(
            index=i,
            timestamp=float(self._t[i]),
            image=image,
            depth=depth,
            T_world_cam=self.frame_pose(i),
            dynamic_mask=mask,
            boxes=self._boxes[i].copy() if self._boxes is not None else None,
        )


def _warn_skip(path: Path, why: str) -> None:
    logger.warning("%s: %s; frame skipped", path, why)


def is_tum_layout(path: Path) -> bool:
    return (path / "rgb.txt").is_file()
