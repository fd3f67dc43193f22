"""Synthetic sequences: a seeded procedural room or street, ray cast with exact depth, poses and IMU.

The embedded default of the demo and the workhorse of unit tests::

    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence, write_sequence

    seq = SyntheticSequence(SyntheticConfig(n_frames=60, loop=True))
    for frame in seq:            # Frames rendered lazily
        ...
    write_sequence(seq, "out")   # TUM RGB-D and EuRoC (ASL) layouts on disk
"""

from vslam.data.synthetic.config import SyntheticConfig
from vslam.data.synthetic.imu import ImuTruth
from vslam.data.synthetic.sequence import SyntheticRender, SyntheticSequence
from vslam.data.synthetic.writer import write_sequence

__all__ = ["ImuTruth", "SyntheticConfig", "SyntheticRender", "SyntheticSequence", "write_sequence"]
