"""KITTI odometry reader behind the Sequence interface.

Layout (https://www.cvlibs.net/datasets/kitti/eval_odometry.php)::

    <root>/sequences/NN/calib.txt     P0..P3 (3x4 rectified projections), optional Tr
    <root>/sequences/NN/times.txt     one time per frame, seconds from the first
    <root>/sequences/NN/image_0..3/   000000.png ... (0/1 left/right grey, 2/3 left/right colour)
    <root>/poses/NN.txt               3x4 T_world_cam0 per line (sequences 00-10 only)

All four cameras are rectified onto one image plane: ``P_i = K [I | t_i]``
with ``t_i`` the position of KITTI camera 0's centre in camera i, so
``T_cam0_cami = [I | -K^-1 P_i[:, 3]]``. For the grey pair that is the
baseline ``-P1[0,3] / P1[0,0]`` along +x.

The body frame of the returned Calibration is the left camera read (KITTI
camera 0 or 2), so ``T_body_cam0`` is the identity; ground-truth poses, given
for KITTI camera 0, are moved onto that camera.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from vslam.data.calibration import check_calibration, check_camera, png_size
from vslam.data.textio import check_increasing, check_rotations, read_numeric, read_rows, require_dir, require_file
from vslam.data.trajectory import Trajectory
from vslam.data.types import Calibration, Frame, PinholeCamera, SensorKind, Sequence
from vslam.errors import DatasetError

logger = logging.getLogger(__name__)

# camera argument -> (left image folder index, right image folder index)
_CAMERA_PAIRS: dict[int, tuple[int, int]] = {0: (0, 1), 2: (2, 3)}


def read_kitti_calib(path: Path) -> dict[str, np.ndarray]:
    """calib.txt -> {"P0": (3,4), ..., "Tr": (3,4)}; every line "KEY: 12 numbers"."""
    lines, rows = read_rows(path, 13, numeric_cols=0)
    out: dict[str, np.ndarray] = {}
    for ln, row in zip(lines, rows):
        key = row[0]
        if not key.endswith(":"):
            raise DatasetError(path, f"expected 'KEY:' then 12 numbers, found {key!r}", ln)
        try:
            vals = np.array([float(v) for v in row[1:]], dtype=np.float64)
        except ValueError:
            bad = next(v for v in row[1:] if not _is_float(v))
            raise DatasetError(path, f"{key} value {bad!r} is not a number", ln) from None
        if not np.all(np.isfinite(vals)):
            raise DatasetError(path, f"{key} holds a value that is not finite", ln)
        out[key[:-1]] = vals.reshape(3, 4)
    return out


def _is_float(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def image_size(files: list[Path], calib_path: Path) -> tuple[int, int]:
    """(width, height) of the first of the images that is a readable PNG; a broken one is skipped later."""
    for f in files[:20]:
        size = png_size(f)
        if size is not None:
            return size
    raise DatasetError(files[0].parent if files else calib_path, "no readable PNG among the first images; cannot tell the image size")


def camera_from_P(P: np.ndarray, width: int, height: int) -> PinholeCamera:
    """Rectified 3x4 projection -> undistorted pinhole camera."""
    return PinholeCamera(width, height, float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]))


def checked_camera(P: dict[str, np.ndarray], key: str, width: int, height: int, calib_path: Path,
                   lines: dict[str, int]) -> PinholeCamera:
    """The camera of ``P[key]``, refused (naming calib.txt, the key, the entry and the line) when its 3x3 part is
    not a rectified K = [[fx 0 cx] [0 fy cy] [0 0 1]] or its numbers are out of range (``check_camera``)."""
    M = P[key][:, :3]
    if abs(M[1, 0]) > 1e-9 or np.abs(M[2] - [0.0, 0.0, 1.0]).max() > 1e-6 or abs(M[0, 1]) > 1e-6 * max(abs(M[0, 0]), 1.0):
        raise DatasetError(calib_path, f"{key} is not a rectified projection K [I | t]: its first three columns must "
                                       "be [[fx 0 cx] [0 fy cy] [0 0 1]], found "
                                       "[" + " ".join(f"{v:g}" for v in M.ravel()) + "]", lines.get(key))
    where = {f: (f"{key} {f} ({key}[{r},{c}])", lines.get(key))
             for f, r, c in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2))}
    where.update({f: (f"{f} of the images", None) for f in ("width", "height")})
    return check_camera(camera_from_P(P[key], width, height), calib_path, where)


def calib_lines(path: Path) -> dict[str, int]:
    """``KEY`` -> its 1-based line in calib.txt (for the errors that name an entry)."""
    out: dict[str, int] = {}
    for n, ln in enumerate(path.read_text(errors="replace").splitlines(), 1):
        key = ln.split(":", 1)[0].strip()
        if ":" in ln and key not in out:
            out[key] = n
    return out


def T_cam0_from_P(P: np.ndarray) -> np.ndarray:
    """T_cam0_cami (4,4) of a rectified P_i = K [I | t_i]: the camera centre at -t_i in camera 0."""
    T = np.eye(4)
    T[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])
    return T


def resolve_sequence_dir(path: Path, sequence: str | int | None) -> tuple[Path, Path | None]:
    """(sequence folder, poses file or None) from a dataset root + sequence or a sequence folder."""
    if (path / "sequences").is_dir():
        if sequence is None:
            found = sorted(p.name for p in (path / "sequences").iterdir() if p.is_dir())
            if len(found) != 1:
                raise DatasetError(path, f"holds sequences {found}; pass sequence='NN' to pick one")
            sequence = found[0]
        name = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        seq_dir = require_dir(path / "sequences" / name, f"KITTI sequence {name}")
        poses = path / "poses" / f"{name}.txt"
    else:
        seq_dir = path
        poses = path.parent.parent / "poses" / f"{path.name}.txt"
        if sequence is not None and str(sequence).lstrip("0") != path.name.lstrip("0"):
            raise DatasetError(path, f"is sequence {path.name}, but sequence={sequence!r} was asked for")
    return seq_dir, poses if poses.is_file() else None


class KittiSequence(Sequence):
    """KITTI odometry sequence.

    path: the dataset root (holding ``sequences/`` and ``poses/``; then
        ``sequence`` names one, e.g. "07", optional when only one is present)
        or a sequence folder ``.../sequences/07`` (poses from ``../../poses/07.txt``).
    sensor: "mono" or "stereo".
    camera: 0 for the grey pair (image_0/image_1), 2 for the colour pair (image_2/image_3).

    Frames: image (370,1226) uint8 grey or (370,1226,3) uint8 BGR, right image
    for stereo, T_world_cam of the left camera read, by frame index.
    """

    def __init__(self, path: str | Path, sensor: str = "mono", camera: int = 0, sequence: str | int | None = None):
        root = require_dir(Path(path), "KITTI")
        if sensor not in ("mono", "stereo"):
            raise DatasetError(root, f"sensor {sensor!r} not available for KITTI; use 'mono' or 'stereo'")
        if camera not in _CAMERA_PAIRS:
            raise DatasetError(root, f"camera must be 0 (grey) or 2 (colour), got {camera!r}")
        seq_dir, poses_path = resolve_sequence_dir(root, sequence)
        self.path = seq_dir
        self.name = f"kitti_{seq_dir.name}"
        self.sensor = cast(SensorKind, sensor)
        self.camera = camera
        self._flags = cv2.IMREAD_GRAYSCALE if camera == 0 else cv2.IMREAD_COLOR
        left_id, right_id = _CAMERA_PAIRS[camera]

        times_path = require_file(seq_dir / "times.txt", "times.txt")
        t_lines, tv = read_numeric(times_path, 1)
        self._t = tv[:, 0].copy()
        if len(self._t) == 0:
            raise DatasetError(times_path, "lists no times")
        check_increasing(times_path, self._t, t_lines)
        self._left = self._image_list(seq_dir, left_id, times_path, t_lines, "")
        self._right = (
            self._image_list(seq_dir, right_id, times_path, t_lines, " (needed for sensor='stereo')") if sensor == "stereo" else None
        )
        self.calibration = self._read_calibration(require_file(seq_dir / "calib.txt", "calib.txt"), left_id, right_id)
        # vslam make-dynamic writes the exact masks of the people it composited (255 = dynamic) beside the images
        self._masks = self._image_list(seq_dir, f"mask_{left_id}", times_path, t_lines, "") if (seq_dir / f"mask_{left_id}").is_dir() else None

        self._gt: Trajectory | None = None
        # A ground-truth problem is raised by groundtruth(), after a run has written its trajectory: it must
        # not stop SLAM, which does not need the ground truth.
        self._gt_error: DatasetError | None = None
        if poses_path is not None:
            try:
                self._gt = self._read_poses(poses_path, times_path)
            except DatasetError as e:
                self._gt_error = e

    def _read_poses(self, poses_path: Path, times_path: Path) -> Trajectory:
        lines, v = read_numeric(poses_path, 12)
        if len(v) < len(self._t):
            raise DatasetError(poses_path, f"has {len(v)} poses for {len(self._t)} frames in {times_path}")
        if len(v) > len(self._t):
            logger.info("%s: %d poses for %d frames; using the first %d", poses_path, len(v), len(self._t), len(self._t))
        T_world_k0 = np.tile(np.eye(4), (len(self._t), 1, 1))
        T_world_k0[:, :3, :4] = v[: len(self._t)].reshape(-1, 3, 4)
        check_rotations(poses_path, T_world_k0[:, :3, :3], lines)
        return Trajectory(self._t, T_world_k0 @ self._T_k0_cam0)

    def _image_list(self, seq_dir: Path, cam_id: int | str, times_path: Path, t_lines: np.ndarray, why: str) -> list[Path]:
        """image_<cam_id>/NNNNNN.png (or the folder ``cam_id`` names) for every line of times.txt; the counts must agree."""
        name = cam_id if isinstance(cam_id, str) else f"image_{cam_id}"
        folder = require_dir(seq_dir / name, f"{name}{why}")
        n_img = sum(1 for p in folder.iterdir() if p.suffix == ".png")
        if n_img != len(self._t):
            raise DatasetError(times_path, f"lists {len(self._t)} times but {folder} holds {n_img} .png images")
        files = [folder / f"{i:06d}.png" for i in range(len(self._t))]
        for i, f in enumerate(files):
            if not f.is_file():
                raise DatasetError(times_path, f"frame {i} has no image {f}", int(t_lines[i]))
        return files

    def _read_calibration(self, calib_path: Path, left_id: int, right_id: int) -> Calibration:
        P = read_kitti_calib(calib_path)
        need = ["P0", f"P{left_id}"] + ([f"P{right_id}"] if self.sensor == "stereo" else [])
        for key in dict.fromkeys(need):
            if key not in P:
                raise DatasetError(calib_path, f"missing {key} (has {', '.join(P) or 'nothing'})")
        width, height = image_size(self._left, calib_path)
        lines = calib_lines(calib_path)
        # every P used is checked before it is inverted (fx = 0 would be a singular K)
        for key in dict.fromkeys(need):
            checked_camera(P, key, width, height, calib_path, lines)
        cam0 = camera_from_P(P[f"P{left_id}"], width, height)
        # Body = the left camera read; KITTI camera 0 is where the poses live.
        self._T_k0_cam0 = T_cam0_from_P(P[f"P{left_id}"]) if left_id != 0 else np.eye(4)
        cam1 = T_body_cam1 = None
        if self.sensor == "stereo":
            cam1 = camera_from_P(P[f"P{right_id}"], width, height)
            T_body_cam1 = np.linalg.inv(self._T_k0_cam0) @ T_cam0_from_P(P[f"P{right_id}"])
        key1 = f"P{right_id}"
        return check_calibration(Calibration(cam0=cam0, cam1=cam1, T_body_cam1=T_body_cam1), calib_path,
                                 baseline=(f"{key1} (baseline -{key1}[0,3] / {key1}[0,0])", lines.get(key1)))

    # -- Sequence interface ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._t)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def groundtruth(self) -> Trajectory | None:
        """T_world_cam of the left camera read, one pose per frame (None without poses/NN.txt); DatasetError
        when the poses file is malformed."""
        if self._gt_error is not None:
            raise self._gt_error
        return self._gt

    # -- extras ------------------------------------------------------------------------

    def frame_pose(self, i: int) -> np.ndarray | None:
        """Ground-truth T_world_cam (4,4) of frame i without decoding its images, or None."""
        return None if self._gt is None else self._gt.poses[i].copy()

    def frame(self, i: int) -> Frame:
        """Frame i with its images decoded; DatasetError if one does not decode."""
        frame = self._load(i)
        if frame is None:
            raise DatasetError(self._left[i], "frame does not decode (see the logged warning)")
        return frame

    def _load(self, i: int) -> Frame | None:
        image = self._imread(self._left[i])
        right = self._imread(self._right[i]) if self._right is not None else None
        if image is None or (self._right is not None and right is None):
            return None
        mask = None
        if self._masks is not None:
            m = cv2.imread(str(self._masks[i]), cv2.IMREAD_GRAYSCALE)
            if m is None:
                logger.warning("%s: mask does not decode; frame skipped", self._masks[i])
                return None
            mask = m > 127
        return Frame(index=i, timestamp=float(self._t[i]), image=image, right=right, T_world_cam=self.frame_pose(i),
                     dynamic_mask=mask)

    def _imread(self, path: Path) -> np.ndarray | None:
        img = cv2.imread(str(path), self._flags)
        if img is None:
            logger.warning("%s: image does not decode; frame skipped", path)
            return None
        cam = self.calibration.cam0
        if img.shape[:2] != (cam.height, cam.width):
            logger.warning("%s: image is %dx%d, the camera's is %dx%d; frame skipped", path, img.shape[1],
                           img.shape[0], cam.width, cam.height)
            return None
        return img


def is_kitti_layout(path: Path) -> bool:
    """A sequence folder (calib.txt + times.txt) or a dataset root with sequences/NN."""
    if (path / "calib.txt").is_file() and (path / "times.txt").is_file():
        return True
    seqs = path / "sequences"
    return seqs.is_dir() and any(p.is_dir() and re.fullmatch(r"\d{2}", p.name) for p in seqs.iterdir())
