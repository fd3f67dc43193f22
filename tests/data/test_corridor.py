"""The synthetic corridor scene (issue 6): plain walls with long edges, few corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.synthetic.corridor import CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT
from vslam.errors import ConfigError
from vslam.features.lines import LineConfig, LineExtractor


def test_corridor_geometry_and_no_loop():
    seq = SyntheticSequence(SyntheticConfig(scene="corridor", n_frames=30, n_movers=0))
    T = seq.groundtruth().poses
    assert np.all(np.abs(T[:, 1, 3]) < CORRIDOR_HALF_WIDTH - 0.8) and np.all((T[:, 2, 3] > 1.0) & (T[:, 2, 3] < CORRIDOR_HEIGHT))
    assert T[-1, 0, 3] - T[0, 0, 3] == pytest.approx(0.8 * 29 / 30, rel=0.15)  # 0.8 m/s down +x
    f = seq.frame(10)
    # the exact depth agrees with the box: every pixel's world point lies inside the corridor
    X = seq.calibration.cam0.backproject(np.stack(np.meshgrid(np.arange(0, 640, 37), np.arange(0, 480, 29)), -1).reshape(-1, 2),
                                         f.depth[::29, ::37].reshape(-1))
    Xw = X @ T[10, :3, :3].T + T[10, :3, 3]
    assert np.all(np.abs(Xw[:, 1]) <= CORRIDOR_HALF_WIDTH + 1e-3) and np.all((Xw[:, 2] >= -1e-3) & (Xw[:, 2] <= CORRIDOR_HEIGHT + 1e-3))
    with pytest.raises(ConfigError):
        SyntheticConfig(scene="corridor", loop=True)


def test_corridor_has_many_segments_and_fewer_corners_than_the_room():
    fast = cv2.FastFeatureDetector_create(12)
    lines = LineExtractor(LineConfig())
    counts = {}
    for scene in ("room", "corridor"):
        seq = SyntheticSequence(SyntheticConfig(scene=scene, n_frames=5, n_movers=0, markers=False))
        img = seq.frame(2).image
        counts[scene] = (len(fast.detect(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))), len(lines.detect(img, seq.calibration.cam0)))
    assert counts["corridor"][0] < 0.3 * counts["room"][0], counts  # few corners
    assert counts["corridor"][1] >= 50, counts  # many long edges
