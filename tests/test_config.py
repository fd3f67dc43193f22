from dataclasses import dataclass, field
from typing import Literal

import pytest

from vslam.config import from_dict, load_config, parse_overrides
from vslam.errors import ConfigError
from vslam.pipeline import PipelineConfig


@dataclass(frozen=True)
class Inner:
    a: int = 1
    mode: Literal["x", "y"] = "x"


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    scale: float = 1.0
    names: tuple[str, ...] = ()


def test_defaults_and_overrides():
    c = from_dict(Outer, {"inner": {"a": 3}, "scale": 2, "names": ["p", "q"]})
    assert c.inner.a == 3 and c.inner.mode == "x" and c.scale == 2.0 and c.names == ("p", "q")


def test_unknown_key_names_key_and_file():
    with pytest.raises(ConfigError, match=r"cfg.yaml: unknown key 'inner.b'"):
        from_dict(Outer, {"inner": {"b": 1}}, "cfg.yaml")


def test_wrong_types_rejected():
    with pytest.raises(ConfigError, match="'inner.a' must be an integer"):
        from_dict(Outer, {"inner": {"a": "three"}})
    with pytest.raises(ConfigError, match="'inner.mode' must be one of"):
        from_dict(Outer, {"inner": {"mode": "z"}})
    with pytest.raises(ConfigError, match="'scale' must be a number"):
        from_dict(Outer, {"scale": True})


def test_exponent_without_a_dot_is_a_number():
    """YAML 1.1 reads 5e-5 as text (its floats need a dot): a float field takes it as the number it writes, from
    --set and from a file; text that is no number is still refused."""
    assert from_dict(Outer, parse_overrides(["scale=5e-5"])).scale == 5e-5
    assert from_dict(Outer, {"scale": "-2E3"}).scale == -2000.0 and from_dict(Outer, {"scale": ".5"}).scale == 0.5
    with pytest.raises(ConfigError, match="'scale' must be a number, got '5e'"):
        from_dict(Outer, {"scale": "5e"})


def test_yaml_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("dataset:\n  kind: [unclosed\n")
    with pytest.raises(ConfigError, match="bad.yaml:"):
        load_config(PipelineConfig, bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(PipelineConfig, tmp_path / "missing.yaml")


def test_every_preset_loads():
    from vslam.resources import preset_names, preset_path

    names = preset_names()
    assert {"synthetic", "tum_rgbd", "kitti_mono", "euroc_stereo_inertial"} <= set(names)
    for name in names:
        PipelineConfig.load(preset_path(name))


def test_parse_overrides():
    assert parse_overrides(["a.b=2", "c=x", "d=[1, 2]"]) == {"a": {"b": 2}, "c": "x", "d": [1, 2]}
    with pytest.raises(ConfigError):
        parse_overrides(["novalue"])


def test_nested_fixed_tuples():
    from vslam.eval import EvalConfig

    c = from_dict(EvalConfig, {"rpe_deltas": [[1, "frames"], [0.5, "meters"]]})
    assert [tuple(d) for d in c.rpe_deltas] == [(1.0, "frames"), (0.5, "meters")]
    with pytest.raises(ConfigError, match="must have 2 items"):
        from_dict(EvalConfig, {"rpe_deltas": [[1, "frames", 3]]})
