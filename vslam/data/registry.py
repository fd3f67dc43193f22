"""Open any supported dataset by path: detect its layout, pick the reader.

    seq = open_sequence("../shared/data/euroc/V1_01_easy_micro", sensor="mono")

Readers are plain classes in a dict (``READERS``); ``DETECTORS`` lists, in
order, how a folder is recognised. To add a family (the synthetic generator
will), add its class to READERS and, if it has a layout of its own, a
detector to DETECTORS; an explicit ``kind=`` always wins over detection.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vslam.data.bag import BagSequence, is_bag
from vslam.data.euroc import EurocSequence, is_euroc_layout
from vslam.data.images import ImageFolderSequence, is_images_layout
from vslam.data.kitti import KittiSequence, is_kitti_layout
from vslam.data.live import LiveSequence
from vslam.data.tum import TumRgbdSequence, is_tum_layout
from vslam.data.types import Sequence
from vslam.data.video import VideoSequence, is_video_file
from vslam.errors import ConfigError, DatasetError

READERS: dict[str, Callable[..., Sequence]] = {
    "tum": TumRgbdSequence,
    "kitti": KittiSequence,
    "euroc": EurocSequence,
    "images": ImageFolderSequence,
    "video": VideoSequence,
    "bag": BagSequence,
    "live": LiveSequence,  # a camera index, stream URL or video file (no layout to detect: kind="live" only)
    # "synthetic": registered by the lead from vslam.data.synthetic (not imported here).
}

# (kind, predicate on the folder, what the predicate looks for -- quoted in the error).
# Order matters: a synthetic sequence in TUM layout must be tested before "tum".
DETECTORS: list[tuple[str, Callable[[Path], bool], str]] = [
    ("tum", is_tum_layout, "rgb.txt (TUM RGB-D)"),
    ("euroc", is_euroc_layout, "mav0/ or cam0/data.csv (EuRoC / TUM-VI)"),
    ("kitti", is_kitti_layout, "calib.txt + times.txt or sequences/NN (KITTI odometry)"),
    ("bag", is_bag, "metadata.yaml (ROS 2 bag)"),
    ("images", is_images_layout, "camera.yaml (image folder)"),
]
# The same for a file: a ROS 1 bag or ROS 2 storage file, a video.
FILE_DETECTORS: list[tuple[str, Callable[[Path], bool], str]] = [
    ("bag", is_bag, ".bag (ROS 1), .db3 / .mcap (ROS 2)"),
    ("video", is_video_file, "a video (.mp4, .avi, .mkv, .mov, ...)"),
]


def detect_kind(path: str | Path) -> str:
    """The READERS key whose layout ``path`` has; DatasetError naming what was looked for."""
    p = Path(path)
    if not p.is_dir() and not p.is_file():
        raise DatasetError(p, "missing dataset folder or file")
    detectors = DETECTORS if p.is_dir() else FILE_DETECTORS
    for kind, matches, _ in detectors:
        if matches(p):
            return kind
    looked_for = "; ".join(what for _, _, what in detectors)
    raise DatasetError(p, f"unknown dataset layout: found none of {looked_for}")


def open_sequence(path: str | Path, kind: str = "auto", **options: Any) -> Sequence:
    """Open the sequence at ``path`` with the reader for ``kind`` ("auto": detected from the layout).

    options go to the reader unchanged, e.g. ``sensor="stereo"``, ``max_diff=0.02``,
    ``sequence="07"``, ``camera=2``; an option the reader does not take is a ConfigError.
    """
    name = detect_kind(path) if kind == "auto" else kind
    reader = READERS.get(name)
    if reader is None:
        raise ConfigError(f"unknown dataset kind {kind!r}; expected auto or one of {', '.join(READERS)}")
    try:
        inspect.signature(reader).bind(path, **options)
    except TypeError as exc:
        raise ConfigError(f"dataset kind {name!r}: {exc}") from None
    return reader(path, **options)
