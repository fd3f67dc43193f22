"""open_sequence layout detection, option passing, errors; datasets/download.py URL table and offline paths."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import urllib.request
import zipfile
from pathlib import Path
from types import ModuleType

import pytest

from tests.data.test_euroc import make_euroc
from tests.data.test_kitti import make_kitti
from tests.data.test_tum import make_tum
from vslam.data.bag import BagSequence
from vslam.data.euroc import EurocSequence
from vslam.data.images import ImageFolderSequence
from vslam.data.kitti import KittiSequence
from vslam.data.live import LiveSequence
from vslam.data.registry import READERS, detect_kind, open_sequence
from vslam.data.tum import TumRgbdSequence
from vslam.data.video import VideoSequence
from vslam.errors import ConfigError, DatasetError

DOWNLOAD = Path(__file__).resolve().parents[2] / "datasets" / "download.py"


def test_readers_table() -> None:
    readers = dict(READERS)
    synthetic = readers.pop("synthetic")
    assert readers == {"tum": TumRgbdSequence, "kitti": KittiSequence, "euroc": EurocSequence,
                       "images": ImageFolderSequence, "video": VideoSequence, "bag": BagSequence, "live": LiveSequence}
    seq = synthetic(sensor="stereo", synthetic={"n_frames": 3, "width": 160, "height": 120})
    assert len(seq) == 3 and seq.frame(0).right is not None


def test_open_dataset_names_the_synthetic_field() -> None:
    from vslam.data.config import DatasetConfig
    from vslam.data.registry import open_dataset

    assert len(open_dataset(DatasetConfig(kind="synthetic", synthetic={"n_frames": 4}))) == 4
    with pytest.raises(ConfigError, match="dataset.synthetic.n_frame"):
        open_dataset(DatasetConfig(kind="synthetic", synthetic={"n_frame": 4}))


def test_detects_each_layout(tmp_path: Path) -> None:
    tum = make_tum(tmp_path / "rgbd_dataset_freiburg3_x")
    euroc = make_euroc(tmp_path / "V1")
    kitti_root = tmp_path / "kitti"
    kitti_seq = make_kitti(kitti_root, seq="05")
    assert detect_kind(tum) == "tum"
    assert detect_kind(euroc) == detect_kind(euroc / "mav0") == "euroc"
    assert detect_kind(kitti_root) == detect_kind(kitti_seq) == "kitti"
    assert isinstance(open_sequence(tum), TumRgbdSequence)
    assert isinstance(open_sequence(euroc / "mav0", sensor="mono"), EurocSequence)
    seq = open_sequence(kitti_root, sequence="05", sensor="stereo")
    assert isinstance(seq, KittiSequence) and seq.sensor == "stereo" and len(seq) == 4


def test_options_reach_the_reader(tmp_path: Path) -> None:
    root = make_tum(tmp_path / "rgbd_dataset_freiburg3_x", depth_offset=0.015)
    assert len(open_sequence(root, max_diff=0.02)) == 5
    with pytest.raises(DatasetError, match=r"depth.txt: no rgb image has a depth image within 0.01 s"):
        open_sequence(root, max_diff=0.01)  # no depth within 10 ms: an RGB-D run would have no depth at all
    assert open_sequence(root, kind="tum", sensor="mono").sensor == "mono"


def test_unknown_layout_names_path_and_what_was_looked_for(tmp_path: Path) -> None:
    (tmp_path / "stuff.txt").write_text("x")
    with pytest.raises(DatasetError) as info:
        open_sequence(tmp_path)
    msg = str(info.value)
    assert msg.startswith(str(tmp_path)) and "unknown dataset layout" in msg
    for wanted in ("rgb.txt", "mav0/", "cam0/data.csv", "calib.txt + times.txt", "sequences/NN"):
        assert wanted in msg


def test_missing_folder_and_bad_kind_or_option(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing dataset folder"):
        open_sequence(tmp_path / "nope")
    root = make_tum(tmp_path / "rgbd_dataset_freiburg3_x")
    with pytest.raises(ConfigError, match="unknown dataset kind 'colmap'"):
        open_sequence(root, kind="colmap")
    with pytest.raises(ConfigError, match="dataset kind 'tum'.*camera"):
        open_sequence(root, camera=2)


@pytest.mark.realdata
def test_real_layouts_detected(tum_teddy: Path, kitti_root: Path, euroc_v101: Path) -> None:
    assert [detect_kind(p) for p in (tum_teddy, kitti_root, kitti_root / "sequences" / "07", euroc_v101)] == ["tum", "kitti", "kitti", "euroc"]
    assert len(open_sequence(kitti_root)) == 160  # the only sequence present is picked


# ------------------------------------------------------------------------------ datasets/download.py


def _load_download() -> ModuleType:
    spec = importlib.util.spec_from_file_location("vslam_datasets_download", DOWNLOAD)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_download_url_table_and_dry_run_without_network(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    dl = _load_download()
    table = dl.url_table()
    url = "https://cvg.cit.tum.de/rgbd/dataset/freiburg3/rgbd_dataset_freiburg3_walking_xyz.tgz"
    assert table["tum/freiburg3_walking_xyz"] == url
    assert table["euroc-legacy/V1_01_easy"] == "http://robotics.ethz.ch/~asl-datasets/ijrr_euroc_mav_dataset/vicon_room1/V1_01_easy/V1_01_easy.zip"
    assert table["euroc/MH_01_easy"].startswith("https://www.research-collection.ethz.ch/")
    assert dl.tum_url("rgbd_dataset_freiburg1_xyz") == dl.tum_url("fr1_xyz")

    def no_network(*args: object, **kwargs: object) -> None:
        raise AssertionError("--dry-run must not touch the network")

    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    assert dl.main(["tum", "fr3_walking_xyz", "--dry-run", "--dest", str(tmp_path)]) == 0
    assert dl.main(["euroc", "V1_01_easy", "--dry-run", "--dest", str(tmp_path)]) == 0
    assert dl.main(["kitti", "--dest", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert url in out and "research-collection.ethz.ch" in out and "registration" in out
    assert list(tmp_path.iterdir()) == []  # nothing written
    assert dl.main(["euroc", "V9_99", "--dry-run"]) == 1

    proc = subprocess.run([sys.executable, str(DOWNLOAD), "tum", "fr3_walking_xyz", "--dry-run"], check=False, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and url in proc.stdout


def test_download_unpacks_nested_euroc_room_zip_and_verifies(tmp_path: Path) -> None:
    """The Research Collection room archive holds <seq>/<seq>.zip; only mav0/ of the wanted one is kept."""
    dl = _load_download()
    src = make_euroc(tmp_path / "src" / "V1_01_easy")
    inner = tmp_path / "V1_01_easy.zip"
    with zipfile.ZipFile(inner, "w") as zf:
        for f in sorted((src / "mav0").rglob("*")):
            if f.is_file():
                zf.write(f, f.relative_to(src).as_posix())
    room = tmp_path / "vicon_room1.zip"
    with zipfile.ZipFile(room, "w") as zf:
        zf.write(inner, "vicon_room1/V1_01_easy/V1_01_easy.zip")
        zf.writestr("vicon_room1/V1_02_medium/V1_02_medium.zip", b"")
    dest = tmp_path / "out" / "euroc"
    dest.mkdir(parents=True)
    dl.extract_euroc(room, "V1_01_easy", dest)
    dl.verify(dest / "V1_01_easy")
    assert len(EurocSequence(dest / "V1_01_easy")) == 5
