"""Our ALIKE with the public weights reproduces the published inference code's outputs
(``pretrained/alike/reference_outputs.npz``, made by Shiaoming/ALIKE on a TUM and a KITTI frame), and the sparse
descriptor head (descriptors at the keypoints only) gives what the dense map gives.

Tolerances: keypoints 0.01 px and descriptor cosine 0.999 are the reference file's own acceptance bounds (its
descriptors are float16, cosine ~0.9998 at best); a wrong layer mapping, a missed BN, another padding, border or
NMS moves keypoints by whole pixels and drops the cosine far below. Score-map rows are float16 (step 2.4e-4 near
0.5): 1e-3. Sparse vs dense is the same arithmetic in another order: 1e-4 px, cosine 0.9999.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from vslam.errors import ConfigError  # noqa: E402
from vslam.nn.registry import KEYPOINTS  # noqa: E402
from vslam.paths import data_root  # noqa: E402

FRAMES = {"tum_teddy_1341841873.305888": "tum/rgbd_dataset_freiburg3_teddy/rgb/1341841873.305888.png",
          "kitti07_000100": "kitti/sequences/07/image_0/000100.png"}


def _need(rel: str):
    p = data_root() / rel
    if not p.exists():
        pytest.skip(f"{p} not found (the public ALIKE weights, their reference outputs and the frames come with "
                    f"the shared data; set VSLAM_DATA)")
    return p


@pytest.fixture(scope="module")
def reference():
    return np.load(_need("pretrained/alike/reference_outputs.npz"))


def _image(tag: str) -> torch.Tensor:
    im = cv2.cvtColor(cv2.imread(str(_need(FRAMES[tag])), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return torch.from_numpy(im).float().permute(2, 0, 1)[None] / 255.0


@pytest.mark.parametrize("variant", ["t", "s"])
def test_reproduces_published_outputs(reference, variant):
    _need(f"pretrained/alike/alike-{variant}.pth")
    model = KEYPOINTS.pretrained(f"alike-{variant}")  # sparse head, top 500, sub-pixel: the reference's settings
    for tag in FRAMES:
        ref = {k: reference[f"alike-{variant}/{tag}/{k}"].astype(np.float32)
               for k in ("keypoints", "scores", "descriptors", "scores_map_rows")}
        with torch.inference_mode():
            out = model({"image": _image(tag)})
        kp, desc = out["keypoints"][0].numpy(), out["descriptors"][0].numpy()
        assert kp.shape == ref["keypoints"].shape
        np.testing.assert_allclose(kp, ref["keypoints"], atol=0.01, err_msg=f"alike-{variant} {tag}")
        np.testing.assert_allclose(out["scores"][0].numpy(), ref["scores"], atol=1e-3)
        assert (desc * ref["descriptors"]).sum(1).min() >= 0.999, f"alike-{variant} {tag}"
        rows = out["scores_map"][0, 0, ::8, ::8].numpy()
        assert rows.shape == ref["scores_map_rows"].shape
        np.testing.assert_allclose(rows, ref["scores_map_rows"], atol=1e-3)


def test_sparse_head_equals_dense_map():
    _need("pretrained/alike/alike-t.pth")
    image = _image("kitti07_000100")[..., :192, :400]  # a crop not a multiple of 32: padding and edges included
    with torch.inference_mode():
        sparse = KEYPOINTS.pretrained("alike-t", {"top_k": 300})({"image": image})
        dense = KEYPOINTS.pretrained("alike-t", {"top_k": 300, "dense": True})({"image": image})
    np.testing.assert_allclose(sparse["keypoints"][0].numpy(), dense["keypoints"][0].numpy(), atol=1e-4)
    cos = (sparse["descriptors"][0] * dense["descriptors"][0]).sum(1)
    assert float(cos.min()) >= 0.9999


def test_other_variant_file_is_one_line_error(tmp_path):
    src = _need("pretrained/alike/alike-t.pth")
    with pytest.raises(ConfigError, match=r"alike-t\.pth: .* ALIKE-s expects"):
        KEYPOINTS.pretrained("alike-s", source=str(src))
    bad = tmp_path / "extra.pth"
    state = torch.load(src, weights_only=True)
    state["convhead1.weight"] = torch.zeros(64, 64, 1, 1)
    torch.save(state, bad)
    with pytest.raises(ConfigError, match="unexpected tensor 'convhead1.weight'"):
        KEYPOINTS.pretrained("alike-t", source=str(bad))


def test_nms_opencv_path_equals_torch_pooling():
    """The CPU path (cv2.dilate) keeps exactly the maxima of the max-pooling path, ties and edges included."""
    from vslam.nn.keypoints.alike import nms

    g = torch.Generator().manual_seed(0)
    for shape in [(1, 1, 37, 53), (2, 1, 64, 80)]:
        x = torch.rand(shape, generator=g)
        x = torch.where(torch.rand(shape, generator=g) < 0.3, (x * 8).round() / 8, torch.zeros(()))  # plateaus
        fast = nms(x, 2)  # float32 on the CPU: OpenCV
        pooled = nms(x.double(), 2).float()  # any other dtype: torch's pooling
        assert torch.equal(fast, pooled)
        assert 0 < int((fast > 0).sum()) < int((x > 0).sum())
