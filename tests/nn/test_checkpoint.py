"""Nothing is loaded with pickle (issue 39): every torch file the package opens (inference weights, a trainer's
``last.pt`` on resume) is read weights-only, and a planted pickle, a checkpoint of another kind, random bytes or a
truncated file is one ``ConfigError`` line naming the file (``vslam: error: ...``, exit 2, from the CLI) -- and
the planted pickle's code never runs."""

from __future__ import annotations

import dataclasses
import pathlib
import pickle

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from vslam.errors import ConfigError  # noqa: E402
from vslam.nn.checkpoint import load_weights, read_checkpoint  # noqa: E402

torch.set_num_threads(1)

TINY_POINT = dict(channels=(8, 16, 16, 32), desc_dim=32)  # the keypoint trainer's toy network
TINY_PLACE = dict(channels=(8, 16, 24, 32), clusters=8, out_dim=64, input_size=(80, 60))
ALL_KEYS = ("model", "config", "names", "state_dict", "meta", "optimizer", "iteration", "train", "opt", "sched",
            "rng", "torch_rng", "stage", "step", "history")


class Planted:
    """Unpickles as ``marker.touch()``: what a crafted checkpoint could run instead."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def _plant(path: pathlib.Path, marker: pathlib.Path, fmt: str) -> pathlib.Path:
    """A file with every key a loader looks for, each value the payload; ``fmt``: torch's zip file or a bare pickle
    (torch's legacy reader)."""
    payload = {k: Planted(marker) for k in ALL_KEYS}
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "zip":
        torch.save(payload, path)
    else:
        path.write_bytes(pickle.dumps(payload, protocol=2))
    return path


def _damaged(path: pathlib.Path, kind: str) -> pathlib.Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "random":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    else:  # a checkpoint cut short (an interrupted copy)
        torch.save({"model": {"w": torch.zeros(4096)}}, path)
        path.write_bytes(path.read_bytes()[:3000])
    return path


def _one_line(err: str, path: pathlib.Path, expected: str) -> None:
    assert "\n" not in err.strip(), err
    assert str(path) in err and expected in err, err


# ------------------------------------------------------------------------------------------- inference loaders


def _detector_weights(path):
    from vslam.dynamic.detector import save_checkpoint
    from vslam.dynamic.model import DetectorConfig, YoloDetector

    return save_checkpoint(path, YoloDetector(DetectorConfig(num_classes=2, width=0.125)), ["person", "car"])


def _convpoint_weights(path):
    from vslam.features.convpoint import ConvPointConfig, ConvPointNet, save_convpoint

    return save_convpoint(ConvPointNet(ConvPointConfig(**TINY_POINT)), path)


def _vladnet_weights(path):
    from vslam.loop.vladnet import VladNet, VladNetConfig, save_vladnet

    return save_vladnet(VladNet(VladNetConfig(**TINY_PLACE)), path)


def _load_model(p):
    from vslam.dynamic.detector import load_model

    return load_model(p)


def _load_detector(p):
    from vslam.dynamic.detector import load_detector

    return load_detector(p)


def _dynamic_filter(p):  # ``slam.dynamic.weights`` as SLAM reads it
    from vslam.data.types import PinholeCamera
    from vslam.dynamic.config import DynamicConfig
    from vslam.dynamic.filter import DynamicFilter

    return DynamicFilter(DynamicConfig(enabled=True, source="detector", weights=str(p), device="cpu"),
                         PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5))


def _convpoint(p):
    from vslam.features.convpoint import load_convpoint

    return load_convpoint(p)


def _convpoint_int8(p):
    from vslam.features.convpoint import load_convpoint

    return load_convpoint(p, int8=True)


def _convpoint_extractor(p):  # ``features.weights`` as SLAM reads it (int8 asked: the float weights are read first)
    from vslam.features.convpoint import _load_extractor_model

    return _load_extractor_model(p, int8=True)


def _vladnet(p):
    from vslam.loop.vladnet import VladNetDescriptor

    return VladNetDescriptor.from_file(p, device="cpu")


def _weights(p):
    return load_weights(p, "test", "vslam train test", lambda c: torch.nn.Linear(1, 1))


LOADERS = {  # loader -> the kind its error names
    "detector.load_model": (_load_model, "not a detector checkpoint"),
    "detector.load_detector": (_load_detector, "not a detector checkpoint"),
    "dynamic.filter": (_dynamic_filter, "not a detector checkpoint"),
    "convpoint": (_convpoint, "not a ConvPoint checkpoint"),
    "convpoint.int8": (_convpoint_int8, "not a ConvPoint checkpoint"),
    "convpoint.extractor": (_convpoint_extractor, "not a ConvPoint checkpoint"),
    "vladnet": (_vladnet, "not a VLADNet checkpoint"),
    "checkpoint.load_weights": (_weights, "not a test checkpoint"),
    "checkpoint.read_checkpoint": (lambda p: read_checkpoint(p, "thing", ("model",)), "not a thing"),
}


def test_the_planted_pickle_runs_its_code_under_the_full_unpickler(tmp_path):
    """The payload is live: were any loader to unpickle it, the marker would appear."""
    for fmt in ("zip", "pickle"):
        marker = tmp_path / f"ran-{fmt}"
        path = _plant(tmp_path / f"{fmt}.pt", marker, fmt)
        with open(path, "rb") as f:
            torch.load(f, weights_only=False) if fmt == "zip" else pickle.load(f)
        assert marker.exists()


@pytest.mark.parametrize("fmt", ["zip", "pickle"])
@pytest.mark.parametrize("loader", sorted(LOADERS))
def test_loaders_refuse_a_planted_pickle_without_running_it(tmp_path, loader, fmt):
    fn, expected = LOADERS[loader]
    marker = tmp_path / "ran"
    path = _plant(tmp_path / "weights.pt", marker, fmt)
    with pytest.raises(ConfigError) as e:
        fn(path)
    _one_line(str(e.value), path, expected)
    assert not marker.exists()
    if fmt == "zip":  # the refused global is named, and why
        assert "never unpickled: that could run code" in str(e.value)


@pytest.mark.parametrize("kind", ["random", "truncated"])
@pytest.mark.parametrize("loader", sorted(LOADERS))
def test_loaders_name_a_damaged_file_in_one_line(tmp_path, loader, kind):
    fn, expected = LOADERS[loader]
    path = _damaged(tmp_path / "weights.pt", kind)
    with pytest.raises(ConfigError) as e:
        fn(path)
    _one_line(str(e.value), path, expected)


@pytest.mark.parametrize("make, loader, why", [
    (_convpoint_weights, "detector.load_detector", "no model, names; it holds config, state_dict, meta"),
    (_convpoint_weights, "dynamic.filter", "no model, names"),
    (_vladnet_weights, "detector.load_model", "no model, names"),
    (_detector_weights, "convpoint", "no state_dict; it holds model, config, names"),
    (_detector_weights, "vladnet", "no state_dict"),
    (_vladnet_weights, "convpoint", "KeyError: 'desc_dim'"),
    (_convpoint_weights, "vladnet", "KeyError: 'clusters'"),
])
def test_a_checkpoint_of_another_kind_is_one_line(tmp_path, make, loader, why):
    fn, expected = LOADERS[loader]
    path = make(tmp_path / "other.pt")
    with pytest.raises(ConfigError) as e:
        fn(path)
    _one_line(str(e.value), path, expected)
    assert why in str(e.value)


def test_read_checkpoint_wants_a_dict_and_names_a_missing_file(tmp_path):
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ConfigError, match=r"list.pt: not a thing \(a list, not a dict\)$"):
        read_checkpoint(tmp_path / "list.pt", "thing")
    with pytest.raises(ConfigError, match=r"gone.pt: thing not found; resume refused$"):
        read_checkpoint(tmp_path / "gone.pt", "thing", note="resume refused")


def test_the_right_kind_still_loads(tmp_path):
    from vslam.dynamic.detector import load_model
    from vslam.features.convpoint import load_convpoint
    from vslam.loop.vladnet import load_vladnet

    model, ck = load_model(_detector_weights(tmp_path / "d.pt"))
    assert ck["names"] == ["person", "car"] and model.cfg.width == 0.125
    assert load_convpoint(_convpoint_weights(tmp_path / "c.pt")).cfg.desc_dim == 32
    assert load_vladnet(_vladnet_weights(tmp_path / "v.pt")).cfg.clusters == 8


# ------------------------------------------------------------------------------------------ trainers' resume


def _keypoint_last(path):
    """A ``last.pt`` as ``vslam train keypoints --toy`` writes it."""
    from vslam.features.convpoint import ConvPointConfig, ConvPointNet
    from vslam.train.keypoints import _optim

    model = ConvPointNet(ConvPointConfig(**TINY_POINT))
    opt, sched = _optim(model, 1e-3, 1e-4, 60)
    torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                "rng": np.random.default_rng(0).bit_generator.state, "torch_rng": torch.get_rng_state(),
                "stage": "shapes", "step": 10, "history": {"shapes": [1.0] * 10, "joint_det": [], "joint_desc": []}}, path)
    return path


def _place_last(path, rng_state=None):
    """A ``last.pt`` as ``vslam train place --toy`` writes it (``rng_state``: another value for its RNG entry)."""
    from vslam.loop.vladnet import VladNet, VladNetConfig

    model = VladNet(VladNetConfig(**TINY_PLACE))
    opt = torch.optim.AdamW(model.parameters())
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=1e-3, total_steps=20)
    rng = np.random.default_rng(0).bit_generator.state if rng_state is None else rng_state
    torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(), "step": 10,
                "history": [1.0] * 10, "rng": rng, "torch_rng": torch.get_rng_state()}, path)
    return path


def _detector_last(path):
    """A ``last.pt`` as ``vslam train detector --toy`` writes it."""
    from vslam.dynamic.detector import save_checkpoint
    from vslam.dynamic.model import DetectorConfig, YoloDetector
    from vslam.train.detector import TrainConfig, resolve

    cfg = resolve(TrainConfig(toy=True))
    model = YoloDetector(DetectorConfig(cfg.scale, cfg.attention, len(cfg.classes), width=cfg.width))
    opt = torch.optim.AdamW(model.parameters())
    return save_checkpoint(path, model, list(cfg.classes), optimizer=opt.state_dict(), iteration=10,
                           train=dataclasses.asdict(cfg))


TRAINERS = {"detector": "not a detector training checkpoint", "keypoints": "not a keypoint training checkpoint",
            "place": "not a place training checkpoint"}


def _resume_cli(out: pathlib.Path, trainer: str, capsys) -> str:
    """``vslam train <trainer> --toy --resume -o out``: exit 2 and the one line on stderr."""
    from vslam.cli import main

    capsys.readouterr()
    assert main(["train", trainer, "--toy", "--resume", "-o", str(out), "--set", "threads=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vslam: error: "), err
    return err


@pytest.mark.parametrize("fmt", ["zip", "pickle"])
@pytest.mark.parametrize("trainer", sorted(TRAINERS))
def test_resume_refuses_a_planted_last_pt_without_running_it(tmp_path, capsys, trainer, fmt):
    marker = tmp_path / "ran"
    last = _plant(tmp_path / "run" / "last.pt", marker, fmt)
    err = _resume_cli(tmp_path / "run", trainer, capsys)
    _one_line(err, last, TRAINERS[trainer])
    assert err.endswith("; resume refused")
    assert not marker.exists()


@pytest.mark.parametrize("kind", ["random", "truncated"])
@pytest.mark.parametrize("trainer", sorted(TRAINERS))
def test_resume_names_a_damaged_last_pt_in_one_line(tmp_path, capsys, trainer, kind):
    last = _damaged(tmp_path / "run" / "last.pt", kind)
    _one_line(_resume_cli(tmp_path / "run", trainer, capsys), last, TRAINERS[trainer])


@pytest.mark.parametrize("trainer, make, why", [
    ("detector", _keypoint_last, "no optimizer, iteration, train"),
    ("detector", _detector_weights, "no optimizer, iteration, train"),  # a model.pt, not a last.pt
    ("keypoints", _place_last, "no stage"),
    ("keypoints", _detector_last, "no opt, sched"),
    ("place", _keypoint_last, "a keypoint training checkpoint"),
    ("place", _detector_last, "no opt, sched"),
])
def test_resume_refuses_another_trainers_last_pt(tmp_path, capsys, trainer, make, why):
    (tmp_path / "run").mkdir()
    last = make(tmp_path / "run" / "last.pt")
    err = _resume_cli(tmp_path / "run", trainer, capsys)
    _one_line(err, last, TRAINERS[trainer])
    assert why in err


def test_an_older_last_pt_with_python_objects_is_refused_not_unpickled(tmp_path, capsys):
    """A ``last.pt`` holding a numpy array (a format the weights-only reader does not take) is refused with the
    reason; resuming from it would need the full unpickler."""
    (tmp_path / "run").mkdir()
    last = _place_last(tmp_path / "run" / "last.pt", rng_state=np.arange(4))
    err = _resume_cli(tmp_path / "run", "place", capsys)
    _one_line(err, last, "not a place training checkpoint")
    assert "that are never unpickled: that could run code" in err and "numpy" in err


def _stop_after_saves(monkeypatch, n: int) -> None:
    """The run is killed right after its ``n``-th ``last.pt``."""
    real_save, saves = torch.save, []

    def save_then_stop(obj, path, *a, **k):
        real_save(obj, path, *a, **k)
        if pathlib.Path(path).name == "last.pt":
            saves.append(path)
            if len(saves) == n:
                raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", save_then_stop)


def _same_weights(a: pathlib.Path, b: pathlib.Path) -> None:
    sa, sb = (torch.load(p / "model.pt", weights_only=True)["state_dict"] for p in (a, b))
    for k in sa:
        torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=0, msg=k)


def test_place_training_resumes_to_the_same_weights(tmp_path, monkeypatch):
    """A toy run killed after its checkpoint at step 10 and resumed from that ``last.pt`` (weights-only) ends
    with the weights of an uninterrupted one."""
    from vslam.train.place import PlaceTrainConfig, train

    cfg = PlaceTrainConfig(out=str(tmp_path / "a"), toy=True, steps=20, threads=1)
    train(cfg)
    cut = dataclasses.replace(cfg, out=str(tmp_path / "b"))
    with monkeypatch.context() as m:
        _stop_after_saves(m, 1)
        with pytest.raises(KeyboardInterrupt):
            train(cut)
    assert read_checkpoint(tmp_path / "b" / "last.pt", "place training checkpoint")["step"] == 10
    train(dataclasses.replace(cut, resume=True))
    _same_weights(tmp_path / "a", tmp_path / "b")


def test_keypoint_training_resumes_to_the_same_weights(tmp_path, monkeypatch):
    """The toy recipe killed in stage 1 (after step 30 of 60) and in stage 3 (after step 10 of 40), each resumed
    from its ``last.pt``: the weights and loss history of the uninterrupted run."""
    from vslam.train.keypoints import KeypointTrainConfig, train

    cfg = KeypointTrainConfig(out=str(tmp_path / "a"), toy=True, threads=1)
    full = train(cfg)
    for saves, stage in ((3, "shapes"), (7, "joint")):  # last.pt every 10 steps: 6 in stage 1, then stage 3's
        cut = dataclasses.replace(cfg, out=str(tmp_path / stage))
        with monkeypatch.context() as m:
            _stop_after_saves(m, saves)
            with pytest.raises(KeyboardInterrupt):
                train(cut)
        assert read_checkpoint(tmp_path / stage / "last.pt", "keypoint training checkpoint")["stage"] == stage
        assert train(dataclasses.replace(cut, resume=True))["loss"] == full["loss"]
        _same_weights(tmp_path / "a", tmp_path / stage)


def test_no_full_unpickler_in_the_package():
    """Every ``torch.load`` under vslam/ passes ``weights_only=True``."""
    root = pathlib.Path(__file__).resolve().parents[2] / "vslam"
    calls = 0
    for f in root.rglob("*.py"):
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if "torch.load(" in line:
                calls += 1
                assert "weights_only=True" in line, f"{f}:{n}: {line.strip()}"
    assert calls >= 1  # the walk found the reader


# ---- the registry's format: {arch, conf, state_dict, meta} ----

def _toy_registry():
    from vslam.nn.registry import Registry

    r = Registry("toy net")
    r.add("tiny", "tests.nn.test_registry:Tiny")
    return r


def test_save_model_round_trip_rebuilds_conf_and_weights(tmp_path):
    from vslam.nn.checkpoint import load_model, save_model

    reg = _toy_registry()
    m = reg.build("tiny", {"width": 6})
    p = save_model(m, tmp_path / "t.pt", "tiny", meta={"source": "test"})
    back, ck = load_model(p, reg)
    assert back.conf == m.conf and ck["meta"] == {"source": "test"} and not back.training
    x = torch.randn(1, 1, 8, 8)
    assert torch.equal(back({"image": x})["heat"], m({"image": x})["heat"])
    half, _ = load_model(save_model(m, tmp_path / "h.pt", "tiny", half=True), reg)
    assert half.a.weight.dtype == torch.float32
    assert torch.allclose(half.a.weight, m.a.weight, atol=1e-3)


def test_load_model_refuses_another_family_or_misfit(tmp_path):
    from vslam.nn.checkpoint import load_model, save_model
    from vslam.nn.registry import Registry

    reg = _toy_registry()
    p = save_model(reg.build("tiny"), tmp_path / "t.pt", "tiny")
    other = Registry("detector")
    with pytest.raises(ConfigError, match=r"t\.pt: not a detector checkpoint \(its network 'tiny' is not a detector"):
        load_model(p, other, "slam.dynamic.weights")
    ck = torch.load(p, weights_only=True)
    ck["conf"]["width"] = 5
    torch.save(ck, p)
    with pytest.raises(ConfigError, match=r"does not fit the network: 'a.weight' is \(4, 1, 3, 3\) in the file, "
                                          r"the network expects \(5, 1, 3, 3\)"):
        load_model(p, reg)
