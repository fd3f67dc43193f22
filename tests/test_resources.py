"""Presets and default weights are package data: found inside the package, all of them in the wheel, and the
old ``configs/<preset>.yaml`` paths still accepted."""

import fnmatch
from pathlib import Path

import pytest
import yaml

import vslam
from vslam.cli import main
from vslam.config import load_config
from vslam.errors import ConfigError
from vslam.pipeline import PipelineConfig
from vslam.resources import preset_description, preset_names, preset_path, resolve_config

PACKAGE = Path(vslam.__file__).resolve().parent
REPO = PACKAGE.parent


def _default_weights() -> list[Path]:
    from vslam.dynamic.detector import default_weights as detector
    from vslam.dynamic.detector import photo_weights
    from vslam.features.alike import VARIANTS, shipped_weights
    from vslam.features.convpoint import default_weights as convpoint
    from vslam.loop.descriptor import default_vladnet_path
    from vslam.loop.vocabulary import default_vocabulary_path

    return [convpoint(), detector(), photo_weights(), default_vladnet_path(), default_vocabulary_path(),
            *(shipped_weights(n) for n in VARIANTS)]


def test_default_weights_are_package_data():
    for w in _default_weights():
        assert w.is_file() and w.resolve().parent == PACKAGE / "models", w


def test_only_default_weights_ship():
    """What vslam/models holds goes into every wheel: the defaults and ConvPoint's int8 ranges, nothing else
    (experiment weights stay in the repository's models/)."""
    convpoint = _default_weights()[0]
    expected = {w.name for w in _default_weights()} | {convpoint.name + ".int8.json"}
    assert {p.name for p in (PACKAGE / "models").iterdir()} == expected


def test_package_data_globs_cover_every_shipped_file():
    tomllib = pytest.importorskip("tomllib", reason="Python 3.11+ reads pyproject.toml")
    globs = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["vslam"]
    shipped = [p.relative_to(PACKAGE).as_posix() for d in ("presets", "models") for p in (PACKAGE / d).iterdir()]
    missing = [f for f in shipped if not any(fnmatch.fnmatch(f, g) for g in globs)]
    assert shipped and not missing


def test_a_preset_resolves_by_name_and_by_its_old_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no configs/ folder here
    p = preset_path("tum_rgbd")
    assert p.parent == PACKAGE / "presets"
    for arg in ("tum_rgbd", "tum_rgbd.yaml", "configs/tum_rgbd.yaml", tmp_path / "elsewhere" / "configs" / "tum_rgbd.yaml"):
        assert resolve_config(arg) == p, arg
    assert load_config(PipelineConfig, "configs/tum_rgbd.yaml") == PipelineConfig.load(p)


def test_an_existing_file_wins_over_a_preset(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").mkdir()
    own = tmp_path / "configs" / "tum_rgbd.yaml"
    own.write_text("dataset:\n  kind: synthetic\n  max_frames: 7\n")
    assert resolve_config("configs/tum_rgbd.yaml") == Path("configs/tum_rgbd.yaml")
    assert PipelineConfig.load("configs/tum_rgbd.yaml").dataset.max_frames == 7


def test_an_unknown_name_is_not_found(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for arg in ("tum_rgbdd", "other/tum_rgbd.yaml"):  # a typo; a preset's name in a folder other than configs/
        assert resolve_config(arg) == Path(arg)
    with pytest.raises(ConfigError, match="tum_rgbdd: config file not found .*vslam presets"):
        PipelineConfig.load("tum_rgbdd")
    with pytest.raises(ConfigError, match="unknown preset 'nope' .*tum_rgbd"):
        preset_path("nope")


def test_every_preset_has_a_one_line_description():
    for name in preset_names():
        d = preset_description(name)
        assert 10 < len(d) < 160 and "\n" not in d and not d.endswith((".", ":", ";")), (name, d)
    assert preset_description("kitti_mono") == "KITTI odometry, left greyscale camera only"


def test_presets_command_lists_each_preset(capsys):
    assert main(["presets"]) == 0
    out = capsys.readouterr().out
    rows = [line.split()[0] for line in out.splitlines() if line and not line.startswith("`")]
    assert rows == preset_names()
    assert "KITTI odometry, left greyscale camera only" in out


def test_run_preset(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", "--preset", "synthetic_stereo", "--max-frames", "4", "--no-eval", "-o", str(out)]) == 0
    written = yaml.safe_load((out / "config.yaml").read_text())
    assert written["dataset"]["sensor"] == "stereo" and written["dataset"]["max_frames"] == 4
    assert main(["run", "--preset", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown preset 'nope'" in err[0]
    with pytest.raises(SystemExit) as e:  # a preset and a config file: argparse refuses the pair
        main(["run", "--preset", "synthetic", "-c", "x.yaml"])
    assert e.value.code == 2
