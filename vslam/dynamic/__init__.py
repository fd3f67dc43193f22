"""Dynamic-object filtering: masks / boxes of moving objects and a geometric motion check decide which
keypoints reach tracking and mapping. The detector's training is in ``vslam.train``, its evaluation in ``vslam.eval``.

Names are resolved lazily (PEP 562) so that ``vslam.dynamic.detector`` / ``model`` load with torch, numpy and
cv2 alone, without the SLAM stack (yaml, scipy, gtsam, pycolmap).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "DynamicConfig": "config", "GeometricConfig": "config", "DynamicFilter": "filter", "GeometricCheck": "motion",
    "dilate": "masking", "in_boxes": "masking", "in_mask": "masking",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'vslam.dynamic' has no attribute {name!r}")
    return getattr(importlib.import_module(f"vslam.dynamic.{_EXPORTS[name]}"), name)
