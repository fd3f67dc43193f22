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


def test_jpeg_quality_recompresses_every_image_and_only_the_images():
    """dataset.jpeg_quality: the colour (and right) images as a JPEG of that quality would give them back; depth
    and ground truth untouched; a quality outside 1-100 is one line naming the field."""
    import cv2

    seq = SyntheticSequence(SyntheticConfig(n_frames=3, width=64, height=48, fx=52.5, fy=52.5, n_movers=0),
                            sensor="stereo")
    sub = select_frames(seq, jpeg_quality=40)
    assert isinstance(sub, Subsequence) and len(sub) == 3
    for raw, lossy in zip(seq, sub):
        for a, b in ((raw.image, lossy.image), (raw.right, lossy.right)):
            ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, 40])
            np.testing.assert_array_equal(b, cv2.imdecode(buf, cv2.IMREAD_UNCHANGED))
            assert b.shape == a.shape and b.dtype == np.uint8 and not np.array_equal(a, b)
        np.testing.assert_array_equal(raw.T_world_cam, lossy.T_world_cam)
    assert PipelineConfig.load(None, {"dataset": {"jpeg_quality": 40}}).dataset.jpeg_quality == 40
    with pytest.raises(ConfigError, match="dataset.jpeg_quality must be 0 .* or a JPEG quality 1-100, got 101"):
        PipelineConfig.load(None, {"dataset": {"jpeg_quality": 101}})


def test_second_room_keeps_the_route_and_the_shape_but_not_the_look():
    """synthetic.second_room: from that frame on the same poses and depth (same box), other textures."""
    cfg = dict(n_frames=4, width=64, height=48, fx=52.5, fy=52.5, n_movers=0)
    one = SyntheticSequence(SyntheticConfig(**cfg))
    two = SyntheticSequence(SyntheticConfig(second_room=2, **cfg))
    for i in range(4):
        a, b = one.frame(i), two.frame(i)
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
        np.testing.assert_array_equal(a.depth, b.depth)
        assert np.array_equal(a.image, b.image) == (i < 2)
    with pytest.raises(ConfigError, match="synthetic.second_room is out of range: 4"):
        SyntheticConfig(second_room=4, **cfg)
