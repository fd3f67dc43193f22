"""Which sequence a run reads: ``DatasetConfig`` (the ``dataset:`` section of a run config)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from vslam.data.bag import BagTopics
from vslam.data.live import LiveConfig
from vslam.data.select import check_jpeg_quality, kept_indices


@dataclass(frozen=True)
class DatasetConfig:
    """Which sequence to run. ``path`` relative to the data root ($VSLAM_DATA or ../shared/data) unless absolute."""

    kind: Literal["auto", "tum", "kitti", "euroc", "synthetic", "images", "video", "bag", "live"] = "synthetic"
    path: str = ""
    sensor: Literal["rgbd", "stereo", "mono"] = "rgbd"
    max_diff: float = 0.02  # seconds, image/depth/ground-truth association
    max_frames: int = 0  # 0 = all frames
    # every stride-th frame, and frame-index ranges [first, last] cut out (a low frame rate, a camera that
    # drops out: ``vslam.data.select``); max_frames counts the frames left
    stride: int = 1
    drop: tuple[tuple[int, int], ...] = ()
    jpeg_quality: int = 0  # 1-100: every image JPEG-compressed at this quality before tracking (0: as read)
    synthetic: dict[str, Any] = field(default_factory=dict)  # SyntheticConfig fields when kind == synthetic
    # your own data (kinds images, video, bag; docs/inputs.md): camera file ("" = camera.yaml beside the data),
    # frame times from a times file or a rate (0 = from the file names / the container / the bag's stamps)
    camera: str = ""
    times: str = ""
    fps: float = 0.0
    topics: BagTopics = BagTopics()
    # kind live: path is a camera index, stream URL, realsense[:SERIAL] or a video file (vslam.data.live)
    live: LiveConfig = LiveConfig()

    def __post_init__(self) -> None:
        kept_indices(0, self.stride, self.drop)  # the same checks as when they are applied
        check_jpeg_quality(self.jpeg_quality)
