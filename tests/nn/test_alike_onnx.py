"""ALIKE's dense part through onnxruntime (``features.runtime: onnxruntime``) gives torch's maps and keypoints:
the same graph exported from the same folded weights, float rounding apart (measured: maps within 1e-5, keypoints
within 2e-4 px, descriptor cosine >= 0.99999 on TUM and KITTI frames). A wrong export (a missed level, another
padding, a fixed input size) moves keypoints by whole pixels or fails at the second image size."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")
pytest.importorskip("onnxruntime")

from scipy.spatial import cKDTree  # noqa: E402

from vslam.errors import ConfigError  # noqa: E402
from vslam.features import FeatureConfig  # noqa: E402
from vslam.features.alike import extract, load_alike, make_maps, torch_maps  # noqa: E402


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for s in (1.5, 3.0, 6.0):
        img += cv2.GaussianBlur(rng.standard_normal(img.shape).astype(np.float32), (0, 0), s) * s
    return cv2.cvtColor(((img - img.min()) / (img.max() - img.min()) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)


@pytest.fixture(scope="module")
def model():
    return load_alike("alike-t")


@pytest.fixture(scope="module")
def onnx(model):
    return make_maps(model, "onnxruntime")


@pytest.mark.parametrize("hw", [(240, 320), (185, 613)])  # TUM and KITTI at half resolution (613: not /32)
def test_maps_equal_torch(model, onnx, hw):
    x = torch.from_numpy(_texture(*hw)).permute(2, 0, 1)[None].float().div(255.0)
    with torch.inference_mode():
        lt, st = torch_maps(model)(x.contiguous(memory_format=torch.channels_last), hw)
    lo, so = onnx(x, hw)
    assert so.shape == st.shape == hw
    np.testing.assert_allclose(so.numpy(), st.numpy(), atol=1e-4)
    for a, b in zip(lo, lt):
        assert a.shape == b.shape
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-4)


def test_keypoints_and_descriptors_equal_torch(model, onnx):
    img = _texture(370, 1226, 1)
    a = extract(model, img, 1000, 0.5)
    b = extract(model, img, 1000, 0.5, maps=onnx)
    d, i = cKDTree(a[0]).query(b[0])
    # near-equal scores may swap at the 1000th place; every other keypoint is the same to float rounding
    assert np.mean(d < 1e-3) > 0.99
    ok = d < 1e-3
    assert (a[2][i[ok]] * b[2][ok]).sum(1).min() > 0.9999
    np.testing.assert_allclose(a[1][i[ok]], b[1][ok], atol=1e-4)


def test_runtime_is_checked():
    with pytest.raises(ConfigError, match="runtime"):
        FeatureConfig(extractor="alike-t", runtime="tensorrt")
    from vslam.features import make_extractor

    ext = make_extractor(FeatureConfig(extractor="alike-t", runtime="onnxruntime"))
    assert type(ext.maps).__name__ == "OnnxMaps"
