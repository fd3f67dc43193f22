"""vslam: visual(-inertial) SLAM among moving objects, with reproducible evaluation."""

import os

# torch's OpenMP threads sleep while they wait instead of spinning. On a small machine shared with other jobs a
# spinning thread team waits at every layer for a member the OS has descheduled, and two torch threads ran many
# times slower than one (docs/speed.md, 'OpenMP wait policy'). It has to be set before torch is first imported
# (OpenMP reads it when loaded); an OMP_WAIT_POLICY already set wins. Child processes inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
