"""The ALIKE extractors of SLAM configs (``features.extractor: alike-t|s|n``): shipped weights, keypoints in the
caller's pixels at any ``input_scale``, masks and grid bucketing honoured, bad names and files one line."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

from vslam.data.types import PinholeCamera  # noqa: E402
from vslam.errors import ConfigError  # noqa: E402
from vslam.features import FeatureConfig, make_extractor  # noqa: E402
from vslam.features.alike import extract, load_alike, shipped_weights  # noqa: E402
from vslam.features.matching import match_mutual  # noqa: E402


def _texture(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    """Blobs at several scales: corners everywhere, none repeated."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h + 40, w + 40), np.float32)
    for s in (1.5, 3.0, 6.0):
        img += cv2.GaussianBlur(rng.standard_normal(img.shape).astype(np.float32), (0, 0), s) * s
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _cam(w: int = 320, h: int = 240) -> PinholeCamera:
    return PinholeCamera(fx=300.0, fy=300.0, cx=w / 2, cy=h / 2, width=w, height=h)


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_keypoints_follow_a_known_shift(scale):
    """A crop shifted by (8, 4) px (whole pixels at half resolution too): matched keypoints differ by that shift.
    Catches a wrong factor from the network's resolution back to the image's (a match then misses by >= 2 px)."""
    big = _texture()
    a, b = big[10:250, 10:330], big[14:254, 18:338]  # b(x, y) = a(x + 8, y + 4)
    ext = make_extractor(FeatureConfig(extractor="alike-t", n_features=500, input_scale=scale))
    fa, fb = ext.detect(a, _cam()), ext.detect(b, _cam())
    assert ext.descriptor_kind == "float" and fa.desc.dtype == np.float32 and fa.desc.shape[1] == 64
    np.testing.assert_allclose(np.linalg.norm(fa.desc, axis=1), 1.0, atol=1e-4)
    m = match_mutual(fa.desc, fb.desc, ratio=None)
    err = np.linalg.norm(fa.raw[m[:, 0]] - (fb.raw[m[:, 1]] + [8, 4]), axis=1)
    assert len(m) > 150
    assert np.median(err) < 0.1 and np.mean(err < 1.0) > 0.8, (np.median(err), np.mean(err < 1))


def test_half_resolution_keypoints_sit_where_full_resolution_ones_do():
    """Pixel centres map as x_full + 0.5 = 2 (x_half + 0.5): the same corners found at both resolutions agree to a
    small fraction of a pixel on average (measured median offset 0.01 / 0.02 px); x_full = 2 x_half would put them
    0.5 px off in x and y."""
    from scipy.spatial import cKDTree

    img, model = _texture(480, 640, 1), load_alike("alike-t")
    full, half = extract(model, img, 1000, 1.0)[0], extract(model, img, 1000, 0.5)[0]
    d, i = cKDTree(full).query(half, distance_upper_bound=2.0)
    ok = np.isfinite(d)
    assert ok.sum() > 300
    assert np.all(np.abs(np.median(half[ok] - full[i[ok]], axis=0)) < 0.15)


def test_mask_and_grid_bucketing():
    img = _texture()
    img[:, 160:] = cv2.GaussianBlur(img[:, 160:], (0, 0), 2.5)  # weaker corners on the right
    cfg = FeatureConfig(extractor="alike-t", n_features=200, grid_cols=4, grid_rows=3, input_scale=1.0)
    ext = make_extractor(cfg)
    model = load_alike("alike-t")
    right_strongest = np.mean(extract(model, img, 200)[0][:, 0] >= 160)
    right_bucketed = np.mean(ext.detect(img, _cam()).raw[:, 0] >= 160)
    assert right_bucketed > right_strongest + 0.1  # the grid gives the weak half its share
    mask = np.zeros(img.shape[:2], bool)
    mask[:, :100] = True  # True: no keypoints wanted here
    f = ext.detect(img, _cam(), mask)
    assert len(f) == 200 and f.raw[:, 0].min() >= 99.0  # sub-pixel refinement may step just across the edge
    strong = make_extractor(FeatureConfig(extractor="alike-t", n_features=200, min_score=0.6, input_scale=1.0)
                            ).detect(img, _cam())
    # the floor is on the peaks; the score reported is sampled at the refined point, a little below its peak
    assert 0 < len(strong) < 200 and strong.response.min() > 0.45


def test_shipped_weights_are_the_public_ones():
    from vslam.nn.registry import KEYPOINTS
    from vslam.paths import data_root

    src = data_root() / "pretrained/alike/alike-t.pth"
    if not src.exists():
        pytest.skip(f"{src} not found (the public ALIKE weights come with the shared data; set VSLAM_DATA)")
    ours = torch.load(shipped_weights("alike-t"), weights_only=True)
    assert ours["arch"] == "alike-t" and ours["meta"]["licence"] == "BSD-3-Clause"
    public = KEYPOINTS.pretrained("alike-t").state_dict()
    for k, v in public.items():  # float16 storage: relative rounding 2^-11
        if v.is_floating_point():
            torch.testing.assert_close(ours["state_dict"][k].float(), v, rtol=1e-3, atol=1e-5)


def test_bad_names_and_files_are_one_line(tmp_path):
    with pytest.raises(ConfigError, match="features.extractor: unknown 'alike-x'"):
        make_extractor(FeatureConfig(extractor="alike-x"))
    with pytest.raises(ConfigError, match="alike_s.pt: an alike-s checkpoint, but features.extractor is alike-t"):
        make_extractor(FeatureConfig(extractor="alike-t", weights=str(shipped_weights("alike-s"))))
    with pytest.raises(ConfigError, match="input_scale must be in"):
        FeatureConfig(extractor="alike-t", input_scale=0.0)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="junk.pt"):
        make_extractor(FeatureConfig(extractor="alike-t", weights=str(junk)))


def test_a_config_naming_alike_gets_its_default_input_scale():
    """``features.input_scale`` unset: ALIKE's own default (half resolution), as ``--set
    slam.features.extractor=alike-t`` in a preset written for ORB gives it; set, the setting."""
    from vslam.features.alike import DEFAULT_INPUT_SCALE

    img = _texture()
    default = make_extractor(FeatureConfig(extractor="alike-t", n_features=300))
    assert default.input_scale == DEFAULT_INPUT_SCALE == 0.5
    half = make_extractor(FeatureConfig(extractor="alike-t", n_features=300, input_scale=0.5))
    np.testing.assert_array_equal(default.detect(img, _cam()).raw, half.detect(img, _cam()).raw)
    assert make_extractor(FeatureConfig(extractor="alike-t", input_scale=1.0)).input_scale == 1.0
