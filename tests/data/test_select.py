"""dataset.stride / dataset.drop: the frames kept, their original indices, the IMU between kept frames."""

from __future__ import annotations

import numpy as np
import pytest

from vslam.data.select import Subsequence, kept_indices, select_frames
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.errors import ConfigError
from vslam.pipeline import PipelineConfig


def test_kept_indices():
    assert kept_indices(12, 5).tolist() == [0, 5, 10]
    assert kept_indices(10, 1, ((2, 4), (8, 20))).tolist() == [0, 1, 5, 6, 7]
    assert kept_indices(20, 3, ((6, 12),)).tolist() == [0, 3, 15, 18]
    with pytest.raises(ConfigError, match="dataset.stride must be at least 1, got 0"):
        kept_indices(5, 0)
    with pytest.raises(ConfigError, match=r"dataset.drop ranges .* got \[4, 2\]"):
        kept_indices(5, 1, ((4, 2),))


def test_config_checks_stride_and_drop():
    cfg = PipelineConfig.load(None, {"dataset": {"stride": 3, "drop": [[60, 119]]}})
    assert cfg.dataset.stride == 3 and cfg.dataset.drop == ((60, 119),)
    with pytest.raises(ConfigError, match="dataset.stride must be at least 1"):
        PipelineConfig.load(None, {"dataset": {"stride": 0}})
    with pytest.raises(ConfigError, match=r"'dataset.drop\[0\]' must have 2 items"):
        PipelineConfig.load(None, {"dataset": {"drop": [[1, 2, 3]]}})


def test_subsequence_keeps_indices_and_the_whole_imu_stream():
    seq = SyntheticSequence(SyntheticConfig(n_frames=14, width=64, height=48, fx=52.5, fy=52.5, n_movers=0))
    assert select_frames(seq) is seq
    sub = select_frames(seq, stride=3, drop=((3, 7),))
    assert isinstance(sub, Subsequence) and len(sub) == 3
    frames = list(sub)
    assert [f.index for f in frames] == [0, 9, 12]
    np.testing.assert_array_equal(sub.timestamps(), seq.timestamps()[[0, 9, 12]])
    full = seq.imu()
    for prev, f in zip(frames, frames[1:]):  # every sample since the previous kept frame, none twice
        want = full.between(prev.timestamp, f.timestamp)
        np.testing.assert_array_equal(f.imu.t, want.t)
        np.testing.assert_array_equal(f.imu.accel, want.accel)
    np.testing.assert_array_equal(frames[0].imu.t, seq.frame(0).imu.t)
    np.testing.assert_array_equal(frames[1].image, seq.frame(9).image)
