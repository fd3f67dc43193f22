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
