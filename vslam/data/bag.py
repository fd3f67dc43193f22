"""ROS 1 and ROS 2 bags through the optional ``rosbags`` package (``pip install vslam[bags]``).

    seq = BagSequence("rgbd_dataset_freiburg3_teddy.bag", sensor="rgbd")

Topics come from ``BagTopics`` (``--set dataset.topics.image=/my/image``); an empty one is the first of its
defaults the bag has, which cover the TUM RGB-D and EuRoC bags. Frame times are the image headers' stamps
(the bag's record time when a stamp is zero); depth images pair with colour images by nearest stamp within
``max_diff`` (as TUM's associate.py). Intrinsics come from a camera file (``camera``; default camera.yaml
beside the bag), else from the image topic's ``camera_info``. IMU samples (sensor_msgs/Imu) ride on the
frames; the camera-IMU extrinsic and noise come from the camera file.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from vslam.data.calibration import check_camera
from vslam.data.camera_file import CAMERA_FILE_NAME, CameraFile, read_camera_file
from vslam.data.association import check as check_pairing
from vslam.data.association import check_depth_image, no_pairs_text
from vslam.data.association import report as pairing_report
from vslam.data.association import associate
from vslam.data.types import Association, Calibration, Frame, ImuSamples, PinholeCamera, SensorKind, Sequence
from vslam.errors import DatasetError

logger = logging.getLogger(__name__)

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
DEFAULT_TOPICS: dict[str, tuple[str, ...]] = {
    "image": ("/camera/rgb/image_color", "/cam0/image_raw", "/camera/color/image_raw", "/camera/image_raw",
              "/image_raw"),
    "depth": ("/camera/depth/image", "/camera/depth/image_raw", "/camera/aligned_depth_to_color/image_raw"),
    "right": ("/cam1/image_raw",),
    "imu": ("/imu0", "/camera/imu"),  # not TUM's /imu: the Kinect accelerometer, no gyro
}
ROS_DEPTH_SCALE = 1000.0  # 16UC1 depth images are millimetres (REP 118)


@dataclass(frozen=True)
class BagTopics:
    """Topic names; "" = the first default (``DEFAULT_TOPICS``) the bag has. camera_info: "" = the image
    topic's namespace + /camera_info."""

    image: str = ""
    depth: str = ""
    right: str = ""
    imu: str = ""
    camera_info: str = ""


def _any_reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DatasetError(path, "reading bags needs the optional 'rosbags' package: pip install 'vslam[bags]'") from None
    # a ROS 2 bag of an older format carries no message definitions: the standard ones
    reader = AnyReader([path.parent if path.suffix in (".db3", ".mcap") else path],
                       default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as e:  # rosbags raises its own per-format errors
        raise DatasetError(path, f"unreadable bag: {e}") from None
    return reader


def _stamp(msg: Any, bag_ns: int) -> float:
    s = msg.header.stamp
    t = int(s.sec) * 10**9 + int(s.nanosec)
    return (t if t > 0 else bag_ns) / 1e9


def decode_image(msg: Any, msgtype: str, where: str) -> np.ndarray:
    """sensor_msgs Image / CompressedImage -> uint8 (H,W) grey or (H,W,3) BGR, uint16 or float32 (H,W) depth."""
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{where}: compressed image ({msg.format}) does not decode")
        return img
    enc = msg.encoding.lower()
    kinds = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
             "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "8uc3": (np.uint8, 3), "mono16": (np.uint16, 1),
             "16uc1": (np.uint16, 1), "32fc1": (np.float32, 1)}
    if enc not in kinds:
        raise ValueError(f"{where}: image encoding {msg.encoding!r} not supported (expected one of {', '.join(kinds)})")
    dtype, ch = kinds[enc]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), np.uint8).reshape(msg.height, msg.step)
    img = rows[:, : msg.width * ch * dt.itemsize].copy().view(dt).reshape(msg.height, msg.width, ch)
    img = img.astype(dtype).squeeze(2) if ch == 1 else img.astype(dtype)
    if enc in ("rgb8", "rgba8"):
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGR)
    elif enc == "bgra8":
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


def camera_from_info(msg: Any, path: Path, topic: str) -> PinholeCamera:
    """sensor_msgs/CameraInfo (ROS 1 ``K``/``D`` or ROS 2 ``k``/``d``) -> PinholeCamera; DatasetError(path)
    naming ``topic`` for what it cannot stand for (an uncalibrated K, a distortion model we do not model)."""
    K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), np.float64).reshape(3, 3)
    D = tuple(float(x) for x in np.asarray(getattr(msg, "d", getattr(msg, "D", ())), np.float64))
    hint = "give the intrinsics in a camera file with --camera (docs/inputs.md)"
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise DatasetError(path, f"{topic}: camera_info has no calibration (K has fx={K[0, 0]:g}, fy={K[1, 1]:g}: "
                                 f"an uncalibrated driver); {hint}")
    model = {"plumb_bob": "radtan", "rational_polynomial": "radtan", "equidistant": "equidistant"}.get(
        msg.distortion_model, "none")
    if not any(D):
        model, D = "none", ()
    elif model == "none":
        raise DatasetError(path, f"{topic}: camera_info distortion model {msg.distortion_model!r} not supported "
                                 f"(plumb_bob, rational_polynomial with k4..k6 zero, equidistant); {hint}")
    elif model == "radtan" and any(D[5:]):  # rational_polynomial's k4 k5 k6 (and s1..s4, tx ty): not modelled
        raise DatasetError(path, f"{topic}: camera_info {msg.distortion_model} distortion with {len(D)} coefficients "
                                 f"(k4..k6 not zero) not supported: radtan takes k1 k2 p1 p2 k3; {hint}")
    elif (model == "radtan" and len(D) < 4) or (model == "equidistant" and len(D) != 4):
        raise DatasetError(path, f"{topic}: camera_info {msg.distortion_model} distortion with {len(D)} "
                                 f"coefficients; {hint}")
    elif model == "radtan":
        D = D[:5]  # what is cut is zeros
    cam = PinholeCamera(int(msg.width), int(msg.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], model, D)  # type: ignore[arg-type]
    where = {f: (f"{topic}: camera_info {f} (K[{k}])", None) for f, k in (("fx", 0), ("fy", 4), ("cx", 2), ("cy", 5))}
    where.update({"width": (f"{topic}: camera_info width", None), "height": (f"{topic}: camera_info height", None),
                  "distortion": (f"{topic}: camera_info D", None)})
    return check_camera(cam, path, where)


class BagSequence(Sequence):
    """Image (and depth / right / IMU) topics of a ROS 1 ``.bag`` or a ROS 2 bag folder (or its .db3/.mcap).

    sensor: "mono", "rgbd" (a depth topic), "stereo" (a right topic; baseline from the camera file).
    Frames: image as published (grey or BGR), depth (H,W) float32 metres (16UC1 / depth_scale, default
    1000; 32FC1 as metres, NaN -> 0), imu: samples since the previous frame. No ground truth.
    """

    def __init__(self, path: str | Path, camera: str | Path | None = None, sensor: str = "mono",
                 topics: BagTopics | dict[str, str] | None = None, max_diff: float = 0.02):
        self.path = Path(path).expanduser()
        if not self.path.exists():
            raise DatasetError(self.path, "missing bag file or folder")
        if sensor not in ("rgbd", "stereo", "mono"):
            raise DatasetError(self.path, f"unknown sensor {sensor!r}; expected rgbd, stereo or mono")
        self.sensor = cast(SensorKind, sensor)
        self.name = self.path.stem
        self.topics = BagTopics(**topics) if isinstance(topics, dict) else topics or BagTopics()
        reader = _any_reader(self.path)
        try:
            self._index(reader, camera, max_diff)
        finally:
            reader.close()
        self._reader: Any = None

    def _topic(self, reader: Any, kind: str, required: bool) -> str | None:
        given = getattr(self.topics, kind)
        have = set(reader.topics)
        if given:
            if given not in have:
                raise DatasetError(self.path, f"no topic {given!r} (dataset.topics.{kind}); the bag has "
                                              f"{', '.join(sorted(have))}")
            return given
        found = next((t for t in DEFAULT_TOPICS[kind] if t in have), None)
        if found is None and required:
            raise DatasetError(self.path, f"none of the default {kind} topics ({', '.join(DEFAULT_TOPICS[kind])}) is "
                                          f"in the bag (it has {', '.join(sorted(have))}); name one with "
                                          f"--set dataset.topics.{kind}=TOPIC")
        return found

    def _scan(self, reader: Any, topic: str) -> tuple[str, np.ndarray, list[tuple[int, int]]]:
        """(topic, header stamps (N,) s sorted, (bag time ns, ordinal at that bag time) per message)."""
        conns = [c for c in reader.connections if c.topic == topic]
        stamps, where = [], []
        seen: dict[int, int] = {}
        for conn, bag_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamps.append(_stamp(msg, bag_ns))
            where.append((bag_ns, seen.get(bag_ns, 0)))
            seen[bag_ns] = seen.get(bag_ns, 0) + 1
        t = np.asarray(stamps, np.float64)
        order = np.argsort(t, kind="stable")
        t, where = t[order], [where[k] for k in order]
        dup = np.flatnonzero(np.diff(t) <= 0)
        if len(dup):
            raise DatasetError(self.path, f"topic {topic}: two messages with the same header stamp {t[dup[0]]:.9f}")
        return topic, t, where

    def _index(self, reader: Any, camera: str | Path | None, max_diff: float) -> None:
        image = cast(str, self._topic(reader, "image", True))
        self._conns = {"image": self._scan(reader, image)}
        if len(self._conns["image"][1]) == 0:
            raise DatasetError(self.path, f"topic {image} holds no message")
        self._t = self._conns["image"][1]
        self._depth_of: list[int] | None = None
        if self.sensor == "rgbd":
            depth_topic = cast(str, self._topic(reader, "depth", True))
            self._conns["depth"] = self._scan(reader, depth_topic)
            t_depth = self._conns["depth"][1]
            ia, ib = associate(self._t, t_depth, max_diff)
            if len(ia) == 0:
                raise DatasetError(self.path, no_pairs_text(self._t, t_depth, "colour", "depth",
                                                            f"within {max_diff:g} s", f"topic {depth_topic}")
                                   + "; check the timestamps, or run with --sensor mono")
            self._depth_of = [-1] * len(self._t)
            for i, j in zip(ia, ib):
                self._depth_of[i] = int(j)
            self.association = pairing_report("rgb-depth", self._t, [f"{image} at {t:.6f} s" for t in self._t], t_depth,
                                              ia, ib, max_diff, f"no depth image within {max_diff:g} s",
                                              unpaired_kept=True)
            check_pairing(self.association, self._t, t_depth, ia, ib, f"{self.path}: {depth_topic}", "colour",
                          "depth", logger)
        if self.sensor == "stereo":
            self._conns["right"] = self._scan(reader, cast(str, self._topic(reader, "right", True)))
            if len(self._conns["right"][1]) != len(self._t) or np.abs(self._conns["right"][1] - self._t).max() > 1e-6:
                raise DatasetError(self.path, "right images' stamps differ from the left images' (a synchronised "
                                              "pair has the same stamp)")
            self.association = Association("left-right", len(self._t), len(self._t), partners=len(self._t),
                                           unpaired_kept=False)
        self._imu = self._read_imu(reader)
        cf = self._camera_file(camera)
        scale_from = f"depth_scale in {cf.path}" if cf is not None else \
            "16UC1 read as millimetres (REP 118); depth_scale in a camera file otherwise"
        try:
            first = self._decode("image", 0, reader)
        except ValueError as e:  # "<bag>:<topic>: image encoding ... not supported" / "... does not decode"
            raise DatasetError(self.path, f"topic {image}, first image: "
                                          f"{str(e).removeprefix(f'{self.path}:{image}: ')}") from None
        if cf is None:
            cam = self._camera_info(reader, image)
            self.calibration = Calibration(cam0=cam, depth_scale=ROS_DEPTH_SCALE if self.sensor == "rgbd" else None)
            if (cam.width, cam.height) != (first.shape[1], first.shape[0]):
                raise DatasetError(self.path, f"camera_info says {cam.width}x{cam.height}, the images are "
                                              f"{first.shape[1]}x{first.shape[0]}")
        else:
            if self.sensor == "stereo" and cf.T_cam0_cam1 is None:
                raise DatasetError(cf.path, "missing key 'baseline' (metres) for --sensor stereo")
            if self.sensor == "rgbd" and cf.depth_scale is None:
                cf = CameraFile(**{**cf.__dict__, "depth_scale": ROS_DEPTH_SCALE})
                scale_from = f"16UC1 read as millimetres (REP 118); depth_scale in {cf.path} otherwise"
            self.calibration = cf.calibration(first.shape[1], first.shape[0], self.sensor, image=self.path)
        if self._depth_of is not None:  # depth no frame can use is refused here, not skipped frame by frame
            j = next(j for j in self._depth_of if j >= 0)
            try:
                raw: np.ndarray | None = self._decode("depth", j, reader)
            except ValueError as e:  # an encoding vslam does not read is refused; a message that does not
                if "not supported" not in str(e):  # decode is skipped later, with its warning
                    raw = None
                else:
                    topic = self._conns["depth"][0]
                    raise DatasetError(self.path, f"topic {topic}, first depth image: "
                                                  f"{str(e).removeprefix(f'{self.path}:{topic}: ')}") from None
            self.depth_median_m = check_depth_image(
                Path(f"{self.path}:{self._conns['depth'][0]}"), raw, (first.shape[1], first.shape[0]),
                (np.uint16, np.float32), "16UC1 (depth_scale units per metre, default millimetres) or 32FC1 (metres) "
                "depth", "images", self.calibration.depth_scale, scale_from)

    def _camera_file(self, camera: str | Path | None) -> CameraFile | None:
        if camera:
            return read_camera_file(Path(camera).expanduser())
        folder = self.path if self.path.is_dir() else self.path.parent
        return read_camera_file(folder / CAMERA_FILE_NAME) if (folder / CAMERA_FILE_NAME).is_file() else None

    def _camera_info(self, reader: Any, image: str) -> PinholeCamera:
        topic = self.topics.camera_info or image.rsplit("/", 1)[0] + "/camera_info"
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            return camera_from_info(reader.deserialize(raw, conn.msgtype), self.path, topic)
        raise DatasetError(self.path, f"no camera file (--camera or camera.yaml beside the bag) and no {topic} "
                                      "messages to take the intrinsics from")

    def _read_imu(self, reader: Any) -> ImuSamples | None:
        topic = self._topic(reader, "imu", False)
        if topic is None:
            return None
        conns = [c for c in reader.connections if c.topic == topic]
        rows = []
        for conn, bag_ns, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            w, a = m.angular_velocity, m.linear_acceleration
            rows.append((_stamp(m, bag_ns), w.x, w.y, w.z, a.x, a.y, a.z))
        v = np.asarray(sorted(rows), np.float64).reshape(-1, 7)
        return ImuSamples(v[:, 0].copy(), v[:, 1:4].copy(), v[:, 4:7].copy(), source=f"{self.path}:{topic}")

    def _decode(self, kind: str, j: int, reader: Any) -> np.ndarray:
        topic, _, where = self._conns[kind]
        conns = [c for c in reader.connections if c.topic == topic]  # a reader's own: they name their owner
        bag_ns, ordinal = where[j]
        msgs = reader.messages(connections=conns, start=bag_ns, stop=bag_ns + 1)
        for k, (conn, _, raw) in enumerate(msgs):
            if k == ordinal:
                return decode_image(reader.deserialize(raw, conn.msgtype), conn.msgtype, f"{self.path}:{conn.topic}")
        raise DatasetError(self.path, f"{kind} message {j} vanished from the bag")

    def __getstate__(self) -> dict[str, Any]:  # sent to the front-end process: it opens the bag itself
        state = self.__dict__.copy()
        state["_reader"] = None
        return state

    # -- Sequence interface ------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._t)

    def timestamps(self) -> np.ndarray:
        return self._t.copy()

    def imu(self) -> ImuSamples | None:
        return self._imu

    def close(self) -> None:
        """Close the open bag reader (the next frame asked for opens it again)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def _load(self, i: int) -> Frame | None:
        if self._reader is None:
            self._reader = _any_reader(self.path)
        try:
            image = self._decode("image", i, self._reader)
            depth = right = None
            if self._depth_of is not None and self._depth_of[i] >= 0:
                raw = self._decode("depth", self._depth_of[i], self._reader)
                if raw.dtype == np.float32:
                    depth = np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
                else:
                    assert self.calibration.depth_scale is not None
                    depth = raw.astype(np.float32) / np.float32(self.calibration.depth_scale)
            if "right" in self._conns:
                right = self._decode("right", i, self._reader)
        except ValueError as e:
            logger.warning("%s; frame %d skipped", e, i)
            return None
        if i + 1 == len(self._t):
            self.close()
        imu = self._imu.between(self._t[i - 1] if i else -np.inf, self._t[i]) if self._imu is not None else None
        return Frame(index=i, timestamp=float(self._t[i]), image=image, depth=depth, right=right, imu=imu)


def is_bag(path: Path) -> bool:
    """A ROS 1 .bag, a ROS 2 storage file, or a ROS 2 bag folder (metadata.yaml beside .db3/.mcap files)."""
    if path.is_file():
        return path.suffix.lower() in BAG_SUFFIXES
    return (path / "metadata.yaml").is_file() and any(p.suffix in (".db3", ".mcap") for p in path.iterdir())
