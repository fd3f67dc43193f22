"""Networks by name: an unknown name or conf key is one line naming what is known; confs merge in the documented
order (architecture default < registry entry < caller); public weights load strictly through a converter."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from vslam.errors import ConfigError  # noqa: E402
from vslam.nn.base import BaseModel  # noqa: E402
from vslam.nn.registry import DETECTORS, KEYPOINTS, PLACES, Registry, family  # noqa: E402


class Tiny(BaseModel):
    """image (B,1,H,W) -> {"heat": (B,1,H,W)}."""

    default_conf = {"width": 4, "act": {"kind": "relu", "slope": 0.0}}
    required_inputs = ("image",)

    def _init(self, conf):
        self.a = torch.nn.Conv2d(1, conf["width"], 3, padding=1)
        self.b = torch.nn.Conv2d(conf["width"], 1, 1)

    def _forward(self, data):
        return {"heat": self.b(torch.relu(self.a(data["image"])))}


def convert_tiny(model, source=None):
    """A "public" state dict under other names, mapped onto ours."""
    torch.manual_seed(0)
    theirs = {f"layer{i}.{k.split('.')[1]}": torch.randn_like(v) for i, (k, v) in
              enumerate(model.state_dict().items())}
    return {k: theirs[f"layer{i}.{k.split('.')[1]}"] for i, k in enumerate(model.state_dict())}


@pytest.fixture
def reg():
    r = Registry("toy net")
    r.add("tiny", f"{__name__}:Tiny", about="a test network")
    r.add("tiny-wide", f"{__name__}:Tiny", {"width": 8}, weights=f"{__name__}:convert_tiny")
    return r


def test_conf_merges_default_entry_caller(reg):
    m = reg.build("tiny-wide", {"act": {"slope": 0.1}})
    assert m.conf == {"width": 8, "act": {"kind": "relu", "slope": 0.1}}
    assert reg.build("tiny").conf["width"] == 4
    assert reg.build("tiny-wide", {"width": 2}).a.out_channels == 2


def test_unknown_name_and_key_are_one_line(reg):
    with pytest.raises(ConfigError, match=r"slam.features.extractor: unknown toy net 'tiny-x' \(known: tiny, tiny-wide\)"):
        reg.build("tiny-x", field_name="slam.features.extractor")
    with pytest.raises(ConfigError, match=r"Tiny: unknown key 'widht' \(known: act, width\)"):
        reg.build("tiny", {"widht": 3})
    with pytest.raises(ConfigError, match=r"Tiny.act: unknown key 'k'"):
        reg.build("tiny", {"act": {"k": 1}})


def test_forward_checks_inputs(reg):
    m = reg.build("tiny")
    assert m({"image": torch.zeros(1, 1, 8, 8)})["heat"].shape == (1, 1, 8, 8)
    with pytest.raises(KeyError, match="needs inputs image"):
        m({"img": torch.zeros(1, 1, 8, 8)})


def test_pretrained_loads_converted_weights_strictly(reg):
    m = reg.pretrained("tiny-wide")
    assert not m.training
    assert torch.equal(m.state_dict()["a.weight"], convert_tiny(reg.build("tiny-wide"))["a.weight"])
    with pytest.raises(ConfigError, match="has no public weights"):
        reg.pretrained("tiny")


def test_double_registration_is_refused(reg):
    with pytest.raises(ValueError, match="registered twice"):
        reg.add("tiny", f"{__name__}:Tiny")


def test_families():
    assert family("detector") is DETECTORS and family("keypoints") is KEYPOINTS and family("place") is PLACES
    with pytest.raises(ConfigError, match="unknown network family"):
        family("segmenter")
