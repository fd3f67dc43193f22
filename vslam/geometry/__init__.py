"""Pure-numpy geometry: rigid transforms, rotations, camera projection."""

from vslam.geometry.se3 import (
    inv_T,
    make_T,
    quat_wxyz_to_R,
    R_to_quat_wxyz,
    so3_exp,
    so3_log,
    skew,
)

__all__ = ["inv_T", "make_T", "quat_wxyz_to_R", "R_to_quat_wxyz", "so3_exp", "so3_log", "skew"]
