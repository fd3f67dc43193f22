"""Loop closing: place descriptors, keyframe database, geometric verification, correction,
relocalisation and map files.

descriptor.py  PlaceDescriptor protocol + bag-of-words baseline (vocabulary.py trains its words)
database.py    keyframe database, top-k by one matrix product
verify.py      descriptor matches to the candidate's map + RANSAC PnP + guided refinement
closing.py     LoopCloser: detect (score floor, temporal consistency), verify, pose graph, fusion, global BA;
               place-recognition relocalisation; final trajectory through keyframes
mapio.py       versioned map file (npz + JSON header) for save / load / localisation-only runs
"""

from typing import Any

__all__ = ["LoopConfig"]


def __getattr__(name: str) -> Any:
    """``LoopConfig`` on first use: its pose-graph settings import gtsam, which the networks (``vladnet``, its
    trainer) must not need (the GPU machine has torch, numpy and cv2 only)."""
    if name == "LoopConfig":
        from vslam.loop.config import LoopConfig

        return LoopConfig
    raise AttributeError(f"module 'vslam.loop' has no attribute {name!r}")
