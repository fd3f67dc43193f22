"""`vslam run --profile` (issue 10): per-stage ms read back from stats.csv add up to the frame time (the
image-only stages computed ahead on the prefetch thread are outside it)."""

from __future__ import annotations

import json

import pytest

from vslam.cli import main
from vslam.profiling import format_profile, profile


@pytest.mark.parametrize("ahead", [False, True], ids=["inline", "ahead"])
def test_profile_of_a_tiny_run(tmp_path, capsys, ahead):
    out = tmp_path / "run"
    rc = main(["run", "--kind", "synthetic", "--max-frames", "15", "-o", str(out), "--profile",
               "--set", "dataset.synthetic.width=320", "--set", "dataset.synthetic.height=240",
               "--set", "dataset.synthetic.fx=262.5", "--set", "dataset.synthetic.fy=262.5",
               "--set", "output.report=false", "--set", f"runtime.frontend_thread={str(ahead).lower()}"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "mean ms/frame" in printed and "peak RSS" in printed
    p = json.loads((out / "profile.json").read_text())
    st = p["stages"]
    assert p["frames"] == 15 and {"decode", "features", "depth", "pose", "mapping", "map_ba", "total"} <= set(st)
    assert st["map_ba"]["frames"] < 15 and st["features"]["frames"] == 15  # BA on keyframes only
    on_thread = ("pose", "mapping") if ahead else ("features", "depth", "pose", "mapping")
    parts = sum(st[k]["mean_ms"] for k in on_thread)
    assert 0.9 * st["total"]["mean_ms"] < parts <= st["total"]["mean_ms"] * 1.001  # the stages make up the frame
    assert st["features"]["mean_ms"] > 0
    assert abs(st["total"]["share"] - 1.0) < 1e-9
    table = format_profile(profile(out / "stats.csv"))
    assert table.splitlines()[0].startswith("stage")
    # the frame rate is that of the whole frame, the wait for the frame (and its features) included
    wall = st["total"]["mean_ms"] + st["decode"]["mean_ms"]
    assert p["wall_ms_per_frame"] == pytest.approx(wall)
    assert f"{1e3 / wall:.1f} frames/s" in table.splitlines()[-1]


def test_network_speed_of_the_learned_front_end(tum_teddy):
    """Every stage of the learned front end is timed on the CPU (the GPU row is measured on a GPU machine)."""
    from vslam.profiling import format_speed, network_speed

    r = network_speed("cpu", frames=2, repeats=1, threads=1)
    assert r["device"] == "cpu" and r["frames"] == 2 and r["peak_gpu_mb"] is None
    assert set(r["ms"]) == {"convpoint", "detector", "lines", "vladnet", "front_end"}
    assert all(v > 0 for v in r["ms"].values())
    assert format_speed([("x", r)])[2].startswith("| x | CPU, 1 threads")
