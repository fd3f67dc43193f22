"""Write a synthetic sequence in the on-disk layouts the dataset readers load.

``tum`` -> ``out_dir/rgbd/`` (TUM RGB-D, https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgb/<t>.png  depth/<t>.png (uint16, metres * 5000, 0 = invalid or beyond 13.1 m)
    rgb.txt depth.txt groundtruth.txt (cam0 in world, at the frame times)
    accelerometer.txt (IMU specific force rotated into cam0 axes, lever arm not applied; IMU rate)
    calibration.yaml (vslam extension: overrides the freiburg intrinsics)
    mask.txt + mask/<t>.png (uint8 0/255)  boxes.txt ("t object_id x1 y1 x2 y2", inclusive pixels)

``asl`` -> ``out_dir/mav0/`` (EuRoC MAV, Burri et al. 2016)::

    cam0/ cam1/ (data.csv, data/<ns>.png grey, sensor.yaml)  imu0/ (data.csv, sensor.yaml)
    state_groundtruth_estimate0/data.csv (BODY frame: p, q wxyz, v, gyro bias, accel bias; IMU rate)

``out_dir/synthetic.yaml`` records the generating config.
"""

from __future__ import annotations

import logging
import os
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Iterable, TextIO

import cv2
import numpy as np
import yaml

from vslam.config import to_dict
from vslam.data.synthetic.sequence import DEPTH_SCALE, SyntheticRender, SyntheticSequence
from vslam.data.trajectory import format_pose
from vslam.geometry.se3 import R_to_quat_wxyz

logger = logging.getLogger(__name__)

LAYOUTS = ("tum", "asl")
PNG_FAST = [cv2.IMWRITE_PNG_COMPRESSION, 1]  # seconds for 300 frames instead of minutes
IMU_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
STATE_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
    "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)


def write_sequence(seq: SyntheticSequence, out_dir: str | Path, layouts: Iterable[str] = LAYOUTS) -> dict[str, Path]:
    """Render every frame once and write the requested layouts.

    Returns {"tum": out_dir/rgbd, "asl": out_dir/mav0} for the layouts written
    (EuRoC readers accept ``mav0`` or its parent ``out_dir``).
    """
    layouts = tuple(layouts)
    unknown = set(layouts) - set(LAYOUTS)
    if unknown:
        raise ValueError(f"unknown layout(s) {sorted(unknown)}; expected a subset of {LAYOUTS}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "synthetic.yaml").write_text(yaml.safe_dump(to_dict(seq.cfg), sort_keys=False))
    roots = {"tum": out / "rgbd", "asl": out / "mav0"}
    start = time.perf_counter()
    # cv2.imwrite releases the GIL: PNG encoding on a few threads while the next frame renders.
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        images = _ImageQueue(pool)
        tum = _TumWriter(seq, roots["tum"], images) if "tum" in layouts else None
        asl = _AslWriter(seq, roots["asl"], images) if "asl" in layouts else None
        for i in range(len(seq)):
            r = seq.render(i, right=asl is not None)
            if tum:
                tum.frame(i, r)
            if asl:
                asl.frame(i, r)
        images.drain()
    for w in (tum, asl):
        if w:
            w.close()
    logger.info("wrote %d frames of %s (%s) in %.1f s", len(seq), seq.name, ", ".join(layouts), time.perf_counter() - start)
    return {k: roots[k] for k in layouts}


class _ImageQueue:
    """PNG writes in flight, bounded so memory stays at a few frames."""

    def __init__(self, pool: ThreadPoolExecutor, max_pending: int = 32):
        self.pool, self.max_pending = pool, max_pending
        self.pending: deque[tuple[Path, Future[bool]]] = deque()

    def write(self, path: Path, img: np.ndarray) -> None:
        self.pending.append((path, self.pool.submit(cv2.imwrite, str(path), img, PNG_FAST)))
        while len(self.pending) > self.max_pending:
            self._finish_one()

    def drain(self) -> None:
        while self.pending:
            self._finish_one()

    def _finish_one(self) -> None:
        path, fut = self.pending.popleft()
        if not fut.result():
            raise OSError(f"could not write {path}")


def _header(f: TextIO, what: str, name: str, columns: str) -> None:
    f.write(f"# {what}\n# file: '{name}'\n# {columns}\n")


class _TumWriter:
    def __init__(self, seq: SyntheticSequence, root: Path, images: _ImageQueue):
        self.seq, self.root, self.images = seq, root, images
        for sub in ("rgb", "depth", "mask"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        self.t = seq.timestamps()
        self.files: dict[str, TextIO] = {}
        for key, what, cols in (
            ("rgb", "color images", "timestamp filename"),
            ("depth", "depth maps", "timestamp filename"),
            ("mask", "dynamic-object masks (synthetic, 255 = moving object)", "timestamp filename"),
            ("boxes", "dynamic-object boxes (synthetic, inclusive pixel bounds)", "timestamp object_id x1 y1 x2 y2"),
        ):
            self.files[key] = open(root / f"{key}.txt", "w")
            _header(self.files[key], what, seq.name, cols)
        self._write_static()

    def _write_static(self) -> None:
        seq, cal = self.seq, self.seq.calibration
        gt = seq.groundtruth()
        with open(self.root / "groundtruth.txt", "w") as f:
            _header(f, "ground truth trajectory", seq.name, "timestamp tx ty tz qx qy qz qw")
            f.writelines(format_pose(t, T, "tum") + "\n" for t, T in zip(gt.timestamps, gt.poses))
        imu = seq.imu()
        acc_cam = imu.accel @ cal.T_body_cam0[:3, :3]  # rows: R_cam_body @ a
        with open(self.root / "accelerometer.txt", "w") as f:
            _header(f, "accelerometer data (synthetic IMU specific force in cam0 axes)", seq.name, "timestamp ax ay az")
            f.writelines(f"{t:.6f} {a[0]:.6f} {a[1]:.6f} {a[2]:.6f}\n" for t, a in zip(imu.t, acc_cam))
        cam = cal.cam0
        (self.root / "calibration.yaml").write_text(
            f"width: {cam.width}\nheight: {cam.height}\nfx: {cam.fx!r}\nfy: {cam.fy!r}\ncx: {cam.cx!r}\ncy: {cam.cy!r}\n"
            f"distortion_model: none\ndistortion: []\ndepth_scale: {DEPTH_SCALE!r}\n"
        )

    def frame(self, i: int, r: SyntheticRender) -> None:
        stamp = f"{self.t[i]:.6f}"
        self.images.write(self.root / "rgb" / f"{stamp}.png", r.image)
        self.images.write(self.root / "depth" / f"{stamp}.png", depth_to_png(r.depth))
        self.images.write(self.root / "mask" / f"{stamp}.png", r.mask.astype(np.uint8) * 255)
        for key in ("rgb", "depth", "mask"):
            self.files[key].write(f"{stamp} {key}/{stamp}.png\n")
        for oid, (x1, y1, x2, y2) in zip(r.box_ids, r.boxes):
            self.files["boxes"].write(f"{stamp} {oid} {x1:.0f} {y1:.0f} {x2:.0f} {y2:.0f}\n")

    def close(self) -> None:
        for f in self.files.values():
            f.close()


def depth_to_png(depth: np.ndarray, scale: float = DEPTH_SCALE) -> np.ndarray:
    """(H,W) float metres -> uint16 raw units; 0 (invalid) where depth <= 0 or beyond the 16-bit range."""
    raw = np.round(depth.astype(np.float64) * scale)
    raw[(raw <= 0) | (raw > 65535)] = 0
    return raw.astype(np.uint16)


def _mat_yaml(T: np.ndarray) -> str:
    rows = [", ".join(repr(float(v)) for v in row) for row in T]
    return "T_BS:\n  cols: 4\n  rows: 4\n  data: [" + ",\n         ".join(rows) + "]\n"


def _rate(hz: float) -> str:
    return str(int(hz)) if float(hz).is_integer() else repr(float(hz))


class _AslWriter:
    def __init__(self, seq: SyntheticSequence, mav0: Path, images: _ImageQueue):
        self.seq, self.mav0, self.images = seq, mav0, images
        self.ns = seq.timestamps_ns()
        self.csv: dict[str, TextIO] = {}
        cal = seq.calibration
        for cam, T in (("cam0", cal.T_body_cam0), ("cam1", cal.T_body_cam1)):
            (mav0 / cam / "data").mkdir(parents=True, exist_ok=True)
            self.csv[cam] = open(mav0 / cam / "data.csv", "w")
            self.csv[cam].write("#timestamp [ns],filename\n")
            (mav0 / cam / "sensor.yaml").write_text(self._camera_yaml(cam, T))
        (mav0 / "body.yaml").write_text("%YAML:1.0\ncomment: vslam synthetic rig (body frame = imu0)\n")
        self._write_imu()
        self._write_state()

    def _camera_yaml(self, cam: str, T: np.ndarray) -> str:
        c = self.seq.calibration.cam0
        return (
            "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n"
            f"comment: vslam synthetic {cam} ({self.seq.name})\n\n# Sensor extrinsics wrt. the body-frame.\n"
            + _mat_yaml(T)
            + f"\n# Camera specific definitions.\nrate_hz: {_rate(self.seq.cfg.fps)}\nresolution: [{c.width}, {c.height}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: [{c.fx!r}, {c.fy!r}, {c.cx!r}, {c.cy!r}] #fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
        )

    def _write_imu(self) -> None:
        imu, n = self.seq.imu(), self.seq.calibration.imu
        assert n is not None
        d = self.mav0 / "imu0"
        d.mkdir(parents=True, exist_ok=True)
        ns = self.seq.imu_timestamps_ns()
        with open(d / "data.csv", "w") as f:
            f.write(IMU_HEADER + "\n")
            f.writelines(f"{t}," + ",".join(f"{v:.12g}" for v in (*g, *a)) + "\n" for t, g, a in zip(ns, imu.gyro, imu.accel))
        (d / "sensor.yaml").write_text(
            "%YAML:1.0\n#Default imu sensor yaml file\nsensor_type: imu\ncomment: vslam synthetic IMU\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n" + _mat_yaml(np.eye(4)) + f"rate_hz: {_rate(n.rate_hz)}\n\n"
            "# inertial sensor noise model parameters (static)\n"
            f"gyroscope_noise_density: {n.gyro_noise_density:.4e}     # [ rad / s / sqrt(Hz) ]   ( gyro \"white noise\" )\n"
            f"gyroscope_random_walk: {n.gyro_random_walk:.4e}       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
            f"accelerometer_noise_density: {n.accel_noise_density:.4e}  # [ m / s^2 / sqrt(Hz) ]   ( accel \"white noise\" )\n"
            f"accelerometer_random_walk: {n.accel_random_walk:.4e}    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n"
        )

    def _write_state(self) -> None:
        truth = self.seq.imu_truth()
        d = self.mav0 / "state_groundtruth_estimate0"
        d.mkdir(parents=True, exist_ok=True)
        q = R_to_quat_wxyz(truth.T_world_body[:, :3, :3])
        cols = np.hstack([truth.T_world_body[:, :3, 3], q, truth.v_world, truth.gyro_bias, truth.accel_bias])
        with open(d / "data.csv", "w") as f:
            f.write(STATE_HEADER + "\n")
            f.writelines(f"{t}," + ",".join(f"{v:.9f}" for v in row) + "\n" for t, row in zip(self.seq.imu_timestamps_ns(), cols))
        (d / "sensor.yaml").write_text(
            "%YAML:1.0\n# General sensor definitions.\nsensor_type: visual-inertial\n"
            "comment: exact ground truth of the synthetic body (imu0) frame.\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n" + _mat_yaml(np.eye(4))
        )

    def frame(self, i: int, r: SyntheticRender) -> None:
        name = f"{self.ns[i]}.png"
        for cam, img in (("cam0", r.image), ("cam1", r.right)):
            assert img is not None
            self.images.write(self.mav0 / cam / "data" / name, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
            self.csv[cam].write(f"{self.ns[i]},{name}\n")

    def close(self) -> None:
        for f in self.csv.values():
            f.close()
