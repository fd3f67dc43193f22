"""Keypoint + descriptor networks of the ``KEYPOINTS`` registry (``vslam.nn.registry``)."""
