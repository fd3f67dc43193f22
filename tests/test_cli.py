"""The CLI turns user mistakes into one line and a non-zero exit, never a traceback."""

import subprocess
import sys

import pytest

from vslam.cli import main


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert "vslam" in capsys.readouterr().out


def test_unknown_config_key_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("dataset:\n  kind: synthetic\n  frobnicate: 3\n")
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key 'dataset.frobnicate'" in err[0] and "c.yaml" in err[0]


def test_missing_dataset_folder_is_one_line(tmp_path, capsys):
    assert main(["run", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0]


def test_eval_bad_file_is_one_line(tmp_path, capsys):
    est = tmp_path / "est.txt"
    est.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0\n")
    gt = tmp_path / "gt.txt"
    gt.write_text("1.0 0 0 0 0 0 0 1\n")
    assert main(["eval", str(est), str(gt)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "est.txt:2" in err[0]


def test_console_script_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "vslam.cli", "eval", str(tmp_path / "a"), str(tmp_path / "b")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1


def test_synth_writes_a_poor_light_corridor(tmp_path, capsys):
    """`vslam synth` reaches every scene and SyntheticConfig field: a dim, noisy corridor in the TUM layout."""
    import cv2
    import numpy as np

    out = tmp_path / "seq"
    assert main(["synth", str(out), "--scene", "corridor", "--frames", "3", "--set", "width=160", "--set", "height=120",
                 "--set", "fx=131.25", "--set", "fy=131.25", "--set", "n_movers=0", "--set", "exposure=0.2",
                 "--set", "image_noise=2"]) == 0
    capsys.readouterr()
    pngs = sorted((out / "rgbd" / "rgb").glob("*.png"))  # the TUM layout (mav0/: the ASL one)
    assert len(pngs) == 3
    img = cv2.imread(str(pngs[0]), cv2.IMREAD_GRAYSCALE).astype(float)
    assert img.mean() < 0.3 * 170 and img.std() > 1.0  # walls ~170 grey at full light; read noise on top
    assert main(["synth", str(tmp_path / "bad"), "--set", "exposure=0"]) == 2
    assert "exposure" in capsys.readouterr().err
