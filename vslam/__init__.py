"""vslam: visual(-inertial) SLAM among moving objects, with reproducible evaluation."""

__version__ = "0.1.0"
