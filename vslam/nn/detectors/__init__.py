"""Detector architectures of the registry (``vslam.nn.registry.DETECTORS``), one module per family."""
