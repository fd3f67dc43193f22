"""Loop closing (issue 7): place descriptors, keyframe database, geometric verification, correction,
relocalisation and map files.

descriptor.py  PlaceDescriptor protocol + bag-of-words baseline (vocabulary.py trains its words)
database.py    keyframe database, top-k by one matrix product
verify.py      descriptor matches to the candidate's map + RANSAC PnP + guided refinement
closing.py     LoopCloser: detect (score floor, temporal consistency), verify, pose graph, fusion, global BA;
               place-recognition relocalisation; final trajectory through keyframes
mapio.py       versioned map file (npz + JSON header) for save / load / localisation-only runs
"""

from vslam.loop.config import LoopConfig

__all__ = ["LoopConfig"]
