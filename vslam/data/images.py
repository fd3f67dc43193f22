"""A folder of images and a camera file: the simplest way to bring your own data.

    seq = ImageFolderSequence("my_run/rgb", camera="my_run/camera.yaml", sensor="rgbd")

Frame times, first found wins: a times file (one timestamp per line, as KITTI's or ORB-SLAM3's EuRoC
times.txt), a frame rate (``fps``, or the camera file's), the file names. A name is a time when its stem is
a decimal number of seconds (TUM: ``1305031102.175304.png``) or a Unix-epoch integer of 10, 13, 16 or 19
digits (s, ms, us, ns; EuRoC: ``1403636579763555584.png``); other names (``000042.png``, ``frame_1.jpg``) are
ordered by name and need a times file or a rate. Depth images pair with colour images by file name, or,
when both are named by time, by nearest time within ``max_diff`` (as TUM's associate.py); right images
pair by file name.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from vslam.data.camera_file import CAMERA_FILE_NAME, CameraFile, read_camera_file
from vslam.data.textio import check_increasing, read_rows
from vslam.data.association import check as check_pairing
from vslam.data.association import check_depth_image, no_pairs_text
from vslam.data.association import report as pairing_report
from vslam.data.association import associate
from vslam.data.types import Association, Frame, SensorKind, Sequence
from vslam.errors import DatasetError

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
_EPOCH_DIGITS = {10: 1.0, 13: 1e-3, 16: 1e-6, 19: 1e-9}  # integer stem length -> seconds per unit


def image_files(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, in natural name order (``2.png`` before ``10.png``)."""
    def key(p: Path) -> list[object]:
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]

    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()), key=key)


def parse_time(token: str) -> float | None:
    """Seconds a file stem or times-file token stands for, None when it is not a time (a frame number)."""
    if re.fullmatch(r"\d+", token):
        unit = _EPOCH_DIGITS.get(len(token))
        return None if unit is None or token.startswith("0") else int(token) * unit
    try:
        v = float(token)
    except ValueError:
        return None
    return v if np.isfinite(v) and re.fullmatch(r"[+-]?(\d+\.\d*|\.\d+|\d+(\.\d*)?[eE][+-]?\d+)", token) else None


def read_times_file(path: Path, n: int, what: str) -> np.ndarray:
    """(n,) s from a file of one timestamp per line; DatasetError when its count is not ``n`` or time goes back."""
    lines, rows = read_rows(path, (1, 2), numeric_cols=1)
    t = np.array([parse_time(r[0]) if parse_time(r[0]) is not None else float(r[0]) for r in rows], np.float64)
    if len(t) != n:
        raise DatasetError(path, f"lists {len(t)} timestamps for {n} {what}; expected one per line, one per frame")
    check_increasing(path, t, np.asarray(lines))
    return t


def frame_times(files: list[Path], times: Path | None, fps: float | None, what: str, folder: Path) -> np.ndarray:
    """Frame times of ``files`` (increasing): from ``times``, else ``fps``, else their names."""
    if times is not None:
        return read_times_file(times, len(files), what)
    if fps:
        return np.arange(len(files), dtype=np.float64) / fps
    t = [parse_time(f.stem) for f in files]
    bad = next((f for f, v in zip(files, t) if v is None), None)
    if bad is not None:
        raise DatasetError(bad, "file name is not a timestamp (seconds like 1305031102.175304, or 10/13/16/19-digit "
                                "epoch s/ms/us/ns); give a times file (--times) or a frame rate (--fps)")
    order = np.argsort(np.asarray(t), kind="stable")
    files[:] = [files[i] for i in order]
    ts = np.asarray(t, np.float64)[order]
    dup = np.flatnonzero(np.diff(ts) <= 0)
    if len(dup):
        raise DatasetError(files[dup[0] + 1], f"same timestamp as {files[dup[0]].name} in {folder}")
    return ts


def find_camera_file(folder: Path, camera: str | Path | None) -> Path:
    """``camera`` if given, else camera.yaml in ``folder`` or its parent (the error names the first)."""
    if camera:
        return Path(camera).expanduser()
    for cand in (folder / CAMERA_FILE_NAME, folder.parent / CAMERA_FILE_NAME):
        if cand.is_file():
            return cand
    return folder / CAMERA_FILE_NAME


def read_depth(path: Path, scale: float, shape: tuple[int, ...]) -> np.ndarray | None:
    """A 16-bit depth PNG -> (H,W) float32 metres, None (logged) when it does not decode to ``shape``."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.shape != shape:
        why = "does not decode" if raw is None else f"is {raw.dtype} {raw.shape}, expected uint16 {shape}"
        logger.warning("%s: depth image %s; frame skipped", path, why)
        return None
    return raw.astype(np.float32) / np.float32(scale)


class ImageFolderSequence(Sequence):
    """Images in a folder (``path``), intrinsics from a camera file (``camera``; default camera.yaml in
    ``path`` or its parent; ``path`` may also be the camera file's folder when the file names ``images``).

    sensor: "mono"; "rgbd" (depth folder from the camera file, else ``depth/`` beside the images; a frame
        without a depth partner has depth=None); "stereo" (right folder and baseline from the camera file,
        else ``right/`` beside the images).
    times / fps: where frame times come from when the names are not times (module docstring).
    max_diff: seconds, colour<->depth matching by time.
    Frames: image as decoded (grey or BGR), depth (H,W) float32 metres, no ground truth.
    """

    def __init__(self, path: str | Path, camera: str | Path | None = None, sensor: str = "mono",
                 times: str | Path | None = None, fps: float = 0.0, max_diff: float = 0.02):
        folder = Path(path).expanduser()
        if not folder.is_dir():
            raise DatasetError(folder, "missing image folder")
        if sensor not in ("rgbd", "stereo", "mono"):
            raise DatasetError(folder, f"unknown sensor {sensor!r}; expected rgbd, stereo or mono")
        cf = read_camera_file(find_camera_file(folder, camera))
        if cf.images is not None and cf.path.parent.resolve() == folder.resolve():
            folder = cf.images
            if not folder.is_dir():
                raise DatasetError(cf.path, f"'images' names {folder}, which is not a folder")
        self.path = folder
        self.name = folder.name if folder.name not in ("rgb", "images", "image", "left", "cam0", "data") \
            else f"{folder.parent.name}/{folder.name}"
        self.sensor = cast(SensorKind, sensor)
        self.camera_file = cf
        self._files = image_files(folder)
        if not self._files:
            raise DatasetError(folder, f"no image files ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        self._t = frame_times(self._files, Path(times).expanduser() if times else None, fps or cf.fps,
                              "images", folder)
        self._depth: list[Path | None] | None = None
        self._right: list[Path] | None = None
        self._check_camera_file()
        if sensor == "rgbd":
            self._depth = self._pair_depth(cf.depth or folder.parent / "depth", max_diff)
        elif sensor == "stereo":
            self._right = self._pair_right(cf.right or folder.parent / "right")
        # the image size (when the camera file leaves it open) and its check come from the first image that
        # decodes; those before it are skipped, warned and counted (``skipped``); none decoding is an error
        first = None
        for k, f in enumerate(self._files):
            first = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if first is not None:
                break
            self._skip(k, "image does not decode")
        if first is None:
            raise DatasetError(folder, f"none of the {len(self._files)} images decodes (first: {self._files[0].name})")
        self.calibration = cf.calibration(first.shape[1], first.shape[0], sensor, image=self._files[k])
        self._first = k
        if self._depth is not None:  # depth no frame can use is refused here, not skipped frame by frame
            d = next(f for f in self._depth if f is not None)
            self.depth_median_m = check_depth_image(
                d, cv2.imread(str(d), cv2.IMREAD_UNCHANGED), (first.shape[1], first.shape[0]), (np.uint16,),
                f"16-bit single-channel depth (uint16, {cf.depth_scale:g} units per metre: depth_scale in the camera "
                "file)", "colour images", self.calibration.depth_scale, f"depth_scale in {cf.path}")

    def _check_camera_file(self) -> None:
        cf = self.camera_file
        if self.sensor == "rgbd" and cf.depth_scale is None:
            raise DatasetError(cf.path, "missing key 'depth_scale' (raw depth units per metre, e.g. 5000 for TUM, "
                                        "1000 for millimetres; DepthMapFactor in ORB-SLAM3 settings)")
        if self.sensor == "stereo" and cf.T_cam0_cam1 is None:
            raise DatasetError(cf.path, "missing key 'baseline' (metres; Stereo.b or Camera.bf in ORB-SLAM3 settings) "
                                        "for --sensor stereo")

    def _pair_depth(self, folder: Path, max_diff: float) -> list[Path | None]:
        if not folder.is_dir():
            raise DatasetError(folder, "missing depth folder for --sensor rgbd (set 'depth' in the camera file, "
                                       "or run with --sensor mono)")
        files = image_files(folder)
        if not files:
            raise DatasetError(folder, "no depth images in the depth folder")
        by_name = {f.name: f for f in files}
        if all(f.name in by_name for f in self._files):
            self.association = Association("rgb-depth", len(self._files), len(self._files), partners=len(files))
            return [by_name[f.name] for f in self._files]
        t_depth = [parse_time(f.stem) for f in files]
        if any(t is None for t in t_depth) or not all(parse_time(f.stem) is not None for f in self._files):
            raise DatasetError(folder, "depth images match the colour images neither by file name nor by "
                                       "timestamp names")
        order = np.argsort(np.asarray(t_depth, np.float64), kind="stable")
        td = np.asarray(t_depth, np.float64)[order]
        ia, ib = associate(self._t, td, max_diff)
        if len(ia) == 0:
            raise DatasetError(folder, no_pairs_text(self._t, td, "colour", "depth", f"within {max_diff:g} s",
                                                     "the depth folder") + "; check the timestamps, or run with --sensor mono")
        out: list[Path | None] = [None] * len(self._files)
        for i, j in zip(ia, ib):
            out[i] = files[order[j]]
        if len(ia) < len(out):
            logger.info("%s: %d of %d images have a depth image within %.3f s; the others get depth=None",
                        folder, len(ia), len(out), max_diff)
        self.association = pairing_report("rgb-depth", self._t, [f.name for f in self._files], td, ia, ib, max_diff,
                                          f"no depth image within {max_diff:g} s", unpaired_kept=True)
        check_pairing(self.association, self._t, td, ia, ib, folder, "colour", "depth", logger)
        return out

    def _pair_right(self, folder: Path) -> list[Path]:
        if not folder.is_dir():
            raise DatasetError(folder, "missing right image folder for --sensor stereo (set 'right' in the camera file)")
        missing = next((f for f in self._files if not (folder / f.name).is_file()), None)
        if missing is not None:
            raise DatasetError(folder / missing.name, "missing right image (right images must have the left names)")
        self.association = Association("left-right", len(self._files), len(self._files), partners=len(self._files),
                                       unpaired_kept=False)
        return [folder / f.name for f in self._files]

    # -- Sequence interface ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._files)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def _skip(self, i: int, why: str, path: Path | None = None) -> None:
        """Warn that frame i is skipped (naming its file) and count it in ``skipped``."""
        path = path or self._files[i]
        logger.warning("%s: %s; frame %d skipped", path, why, i)
        self.skipped.append((i, f"{path.name}: {why}"))

    def _load(self, i: int) -> Frame | None:
        if i < self._first:  # found undecodable when the folder was opened: warned and counted then
            return None
        image = cv2.imread(str(self._files[i]), cv2.IMREAD_UNCHANGED)
        cam = self.calibration.cam0
        if image is None or image.dtype != np.uint8 or image.shape[:2] != (cam.height, cam.width):
            why = "does not decode" if image is None else (
                f"is {image.dtype}, expected 8-bit" if image.dtype != np.uint8 else
                f"is {image.shape[1]}x{image.shape[0]}, the camera's is {cam.width}x{cam.height}")
            self._skip(i, f"image {why}")
            return None
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        depth = right = None
        if self._depth is not None and self._depth[i] is not None:
            assert self.calibration.depth_scale is not None
            depth = read_depth(self._depth[i], self.calibration.depth_scale, image.shape[:2])  # type: ignore[arg-type]
            if depth is None:  # warned by read_depth
                self.skipped.append((i, f"{self._depth[i].name}: depth image does not decode to the image's size"))  # type: ignore[union-attr]
                return None
        if self._right is not None:
            right = cv2.imread(str(self._right[i]), cv2.IMREAD_GRAYSCALE if image.ndim == 2 else cv2.IMREAD_COLOR)
            if right is None or right.shape != image.shape:
                self._skip(i, "right image does not decode to the left one's shape", self._right[i])
                return None
        return Frame(index=i, timestamp=float(self._t[i]), image=image, depth=depth, right=right)


def is_images_layout(path: Path) -> bool:
    """A folder holding camera.yaml, or image files with camera.yaml one level up."""
    if (path / CAMERA_FILE_NAME).is_file():
        return True
    return (path.parent / CAMERA_FILE_NAME).is_file() and any(
        p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())


__all__ = ["CameraFile", "ImageFolderSequence", "frame_times", "image_files", "is_images_layout", "parse_time"]
