"""Builders for the user-data inputs (image folder, video, ROS 1 / ROS 2 bag) from a list of frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

TEDDY_CAMERA = "fx: 535.4\nfy: 539.2\ncx: 320.1\ncy: 247.6\nwidth: 640\nheight: 480\n"  # TUM freiburg3


def write_video(path: Path, images: list[np.ndarray], fps: float = 30.0) -> Path:
    """A lossless FFV1 .avi of BGR ``images``."""
    h, w = images[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h))
    assert writer.isOpened(), "OpenCV cannot write FFV1 here"
    for im in images:
        writer.write(im)
    writer.release()
    return path


def _stamp(types, t: float):
    sec, frac = f"{t:.9f}".split(".")
    return types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(frac))


def write_bag(path: Path, ros: int, rgb: list[tuple[float, Path]], depth: list[tuple[float, Path]],
              depth_encoding: str = "32FC1", depth_scale: float = 5000.0, camera_info: bool = True,
              imu: list[tuple[float, np.ndarray, np.ndarray]] = ()) -> Path:
    """A ROS ``ros`` (1 or 2) bag with TUM's topic names: rgb8 images, depth as 32FC1 metres or 16UC1 raw,
    the teddy camera_info, and sensor_msgs/Imu samples (t, gyro, accel) on /imu0."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    T = ts.types
    if ros == 1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=9), ts.serialize_cdr

    def header(t: float):
        kw = {"seq": 0} if ros == 1 else {}
        return T["std_msgs/msg/Header"](**kw, stamp=_stamp(T, t), frame_id="camera")

    def image(t: float, img: np.ndarray, enc: str):
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).view(np.uint8).reshape(-1)
        return T["sensor_msgs/msg/Image"](header=header(t), height=h, width=w, encoding=enc, is_bigendian=0,
                                          step=data.size // h, data=data)

    msgs: list[tuple[int, str, object]] = []
    for t, f in rgb:
        msgs.append((round(t * 1e9), "/camera/rgb/image_color",
                     image(t, cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB), "rgb8")))
    for t, f in depth:
        raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        d = (raw.astype(np.float32) / np.float32(depth_scale)) if depth_encoding == "32FC1" else raw
        msgs.append((round(t * 1e9), "/camera/depth/image", image(t, d, depth_encoding)))
    if camera_info:
        K = np.array([535.4, 0, 320.1, 0, 539.2, 247.6, 0, 0, 1], np.float64)
        R = np.eye(3).reshape(-1)
        P = np.array([535.4, 0, 320.1, 0, 0, 539.2, 247.6, 0, 0, 0, 1, 0], np.float64)
        keys = ("D", "K", "R", "P") if ros == 1 else ("d", "k", "r", "p")
        info = T["sensor_msgs/msg/CameraInfo"](
            header=header(rgb[0][0]), height=480, width=640, distortion_model="plumb_bob",
            **dict(zip(keys, (np.zeros(5), K, R, P))), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        msgs.append((round(rgb[0][0] * 1e9), "/camera/rgb/camera_info", info))
    for t, w, a in imu:
        V = T["geometry_msgs/msg/Vector3"]
        Q = T["geometry_msgs/msg/Quaternion"]
        cov = np.zeros(9)
        msgs.append((round(t * 1e9), "/imu0", T["sensor_msgs/msg/Imu"](
            header=header(t), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
            angular_velocity=V(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=cov,
            linear_acceleration=V(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=cov)))
    with writer:
        conns = {}
        for bag_ns, topic, msg in sorted(msgs, key=lambda m: m[0]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=ts)
            writer.write(conns[topic], bag_ns, ser(msg, msg.__msgtype__))
    return path
