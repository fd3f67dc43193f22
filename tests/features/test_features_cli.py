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


def test_train_keypoints_toy_from_the_cli(tmp_path, capsys):
    assert main(["train", "keypoints", "--toy", "-o", str(tmp_path / "kp"), "--set", "threads=1"]) == 0
    assert (tmp_path / "kp" / "model.pt").is_file() and (tmp_path / "kp" / "log.jsonl").is_file()
    printed = json.loads(capsys.readouterr().out)
    assert printed["loss"]["shapes"]["last"] < printed["loss"]["shapes"]["first"]
