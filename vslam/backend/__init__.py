"""The only place GTSAM factor graphs are built: local bundle adjustment and pose-only refinement.

Later issues add line, loop and IMU factors here. Inputs and outputs are numpy;
GTSAM types never leave this package.
"""
