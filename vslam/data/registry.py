"""Open any supported dataset by path: detect its layout, pick the reader.

    seq = open_sequence("../shared/data/euroc/V1_01_easy_micro", sensor="mono")

Readers are plain classes in a dict (``READERS``); ``DETECTORS`` lists, in
order, how a folder is recognised. To add a family, add its class to READERS
and, if it has a layout of its own, a detector to DETECTORS; an explicit
``kind=`` always wins over detection. ``open_dataset`` opens what a run
config's ``dataset:`` section names (the synthetic generator included).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vslam.data.bag import BagSequence, is_bag
from vslam.data.config import DatasetConfig
from vslam.data.euroc import EurocSequence, is_euroc_layout
from vslam.data.images import ImageFolderSequence, is_images_layout
from vslam.data.kitti import KittiSequence, is_kitti_layout
from vslam.data.live import LiveSequence
from vslam.data.tum import TumRgbdSequence, is_tum_layout
from vslam.data.types import Sequence
from vslam.data.video import VideoSequence, is_video_file
from vslam.errors import ConfigError, DatasetError
from vslam.paths import data_root

def _synthetic(path: str | Path = "", sensor: str = "rgbd", synthetic: dict[str, Any] | None = None) -> Sequence:
    """The synthetic generator as a reader: ``synthetic`` holds ``SyntheticConfig`` fields (config section
    ``dataset.synthetic``); imported on use, like the renderer it needs."""
    from vslam.config import from_dict
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence

    scfg = from_dict(SyntheticConfig, dict(synthetic or {}), "dataset.synthetic", prefix="dataset.synthetic.")
    return SyntheticSequence(scfg, sensor=sensor)


READERS: dict[str, Callable[..., Sequence]] = {
    "tum": TumRgbdSequence,
    "kitti": KittiSequence,
    "euroc": EurocSequence,
    "images": ImageFolderSequence,
    "video": VideoSequence,
    "bag": BagSequence,
    "live": LiveSequence,  # a camera index, stream URL or video file (no layout to detect: kind="live" only)
    "synthetic": _synthetic,  # generated in memory from a SyntheticConfig dict (no path)
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


def open_dataset(cfg: DatasetConfig) -> Sequence:
    """The Sequence a DatasetConfig names (synthetic ones are generated lazily in memory)."""
    if cfg.kind == "synthetic":
        return open_sequence("", kind="synthetic", sensor=cfg.sensor, synthetic=dict(cfg.synthetic))
    if cfg.kind == "live":  # frames as they come: nothing to select from, a queue that drops instead
        if cfg.stride != 1 or cfg.drop:
            raise ConfigError("dataset.stride and dataset.drop select frames of a recording; a live source has "
                              "none to select (its queue drops the frames the tracker cannot take)")
        return open_sequence(cfg.path, kind="live", camera=_data_path(cfg.camera), sensor=cfg.sensor,
                             config=cfg.live)
    if not cfg.path:
        raise ConfigError("dataset.path is empty; give the sequence folder (or use kind: synthetic)")
    path = Path(cfg.path).expanduser()
    if not path.is_absolute() and not path.exists():
        path = data_root() / path
    layout = _layout(path)
    kind = layout if cfg.kind == "auto" else cfg.kind
    if layout is not None and kind != layout:
        raise ConfigError(f"dataset.kind is {kind!r} but {path} has the {layout} layout; use a config for "
                          f"{layout} (or --kind {layout} with --sensor)")
    if kind is None and cfg.camera and path.is_dir():  # a plain image folder, its camera file given apart
        kind = "images"
    if kind is None:
        kind = detect_kind(path)  # raises, naming what it looked for
    options: dict[str, Any] = {"sensor": cfg.sensor}
    if kind in ("tum", "euroc", "images", "bag"):  # KITTI frames are matched by index, not time
        options["max_diff"] = cfg.max_diff
    if kind in ("images", "video", "bag"):
        options.update(camera=_data_path(cfg.camera), **({"topics": cfg.topics} if kind == "bag" else
                                                          {"times": _data_path(cfg.times), "fps": cfg.fps}))
    return open_sequence(path, kind=kind, **options)


def _data_path(p: str) -> Path | None:
    """A user-given file path (camera, times) as given, None when empty."""
    return Path(p).expanduser() if p else None


def _layout(path: Path) -> str | None:
    """The dataset kind ``path``'s layout shows, None when it shows none."""
    try:
        return detect_kind(path)
    except DatasetError:
        return None
