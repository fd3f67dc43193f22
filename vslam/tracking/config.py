"""``SlamConfig``: the ``slam:`` section of a run config, one field per part of the SLAM system."""

from __future__ import annotations

from dataclasses import dataclass, field

from vslam.backend.ba import BackendConfig
from vslam.dynamic import DynamicConfig
from vslam.features import FeatureConfig
from vslam.features.lines import LineConfig
from vslam.loop.config import LoopConfig
from vslam.mapping.local_mapping import MappingConfig
from vslam.tracking.atlas import AtlasConfig
from vslam.tracking.dense import DenseConfig
from vslam.tracking.initializer import InitConfig
from vslam.tracking.tracker import TrackingConfig
from vslam.tracking.vio import VioConfig


@dataclass(frozen=True)
class SlamConfig:
    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    init: InitConfig = field(default_factory=InitConfig)
    init_ba: bool = True  # monocular: BA of the two initial keyframes
    # monocular: once the map exists, localise the frames seen before it against the initial map (PnP); the
    # pipeline writes them into trajectory_final.tum.txt (trajectory.tum.txt keeps what was known per frame)
    backfill: bool = True
    loop: LoopConfig = field(default_factory=LoopConfig)  # loop closing + place relocalisation (vslam.loop)
    load_map: str = ""  # start from a map saved by save_map (vslam.loop.mapio)
    localize_only: bool = False  # with load_map: track against the saved map, never add keyframes
    save_map: bool = False  # finish() also writes map.vslam.npz (keyframes, points, place descriptors)
    inertial: VioConfig = field(default_factory=VioConfig)  # visual-inertial mode (vslam.tracking.vio), off by default
    lines: LineConfig = field(default_factory=LineConfig)  # point + Plücker-line features, off by default
    dynamic: DynamicConfig = field(default_factory=DynamicConfig)  # dynamic-object filtering, off by default
    dense: DenseConfig = field(default_factory=DenseConfig)  # RGB-D: depth ICP where features fail (tracking.dense)
    # tracking lost: a new map, and maps merged where they meet (``vslam.tracking.atlas``)
    atlas: AtlasConfig = field(default_factory=AtlasConfig)
