"""``vslam eval-features`` and ``vslam train keypoints`` from the command line (issue 4)."""

from __future__ import annotations

import json

from vslam.cli import main


def test_eval_features_writes_results_and_table(tum_teddy, tmp_path, capsys):
    out = tmp_path / "feat"
    assert main(["eval-features", "--images", "1", "--pairs", "1", "--methods", "orb,convpoint", "-o", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    assert set(res["homography"]["illumination"]) == {"orb", "convpoint"}
    assert "| illumination | convpoint |" in (out / "table.md").read_text()
    assert "epipolar inlier ratio" in capsys.readouterr().out


def test_eval_features_missing_weights_is_one_line(tmp_path, capsys):
    assert main(["eval-features", "--weights", str(tmp_path / "none.pt"), "--methods", "convpoint"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.pt: ConvPoint weights not found" in err[0]


def test_eval_features_unknown_method_is_one_line(capsys):
    assert main(["eval-features", "--methods", "orb,superpoint"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown feature method(s) superpoint" in err[0] and "convpoint-int8" in err[0]


def test_quantize_keypoints_writes_ranges_beside_the_weights(tum_teddy, tmp_path, capsys):
    from vslam.features.convpoint import ConvPointInt8, load_convpoint

    w = _copy_of_shipped(tmp_path)
    assert main(["quantize", "keypoints", "--weights", str(w), "--per-source", "1"]) == 0
    assert f"wrote {w}.int8.json" in capsys.readouterr().out
    doc = json.loads((tmp_path / "cp.pt.int8.json").read_text())
    assert doc["meta"]["per_source"] == 1 and doc["meta"]["images"] >= 2  # one image of each source present
    assert isinstance(load_convpoint(w, int8=True), ConvPointInt8)


def test_without_data_quantize_and_eval_features_say_so_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("VSLAM_DATA", str(tmp_path / "nothing"))
    for argv in (["quantize", "keypoints", "--weights", str(_copy_of_shipped(tmp_path))], ["eval-features", "--methods", "orb"]):
        assert main(argv) == 2
        err = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.startswith("vslam: error")]
        assert len(err) == 1 and "nothing: no " in err[0] and "set VSLAM_DATA" in err[0]


def _copy_of_shipped(tmp_path):
    import shutil

    from vslam.features.convpoint import default_weights

    return shutil.copy(default_weights(), tmp_path / "cp.pt")


def test_train_keypoints_toy_from_the_cli(tmp_path, capsys):
    assert main(["train", "keypoints", "--toy", "-o", str(tmp_path / "kp"), "--set", "threads=1"]) == 0
    assert (tmp_path / "kp" / "model.pt").is_file() and (tmp_path / "kp" / "log.jsonl").is_file()
    printed = json.loads(capsys.readouterr().out)
    assert printed["loss"]["shapes"]["last"] < printed["loss"]["shapes"]["first"]
