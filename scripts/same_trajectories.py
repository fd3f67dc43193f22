"""Refactoring guard: run a fixed set of configurations and record a hash of every trajectory and map they write,
or compare against a record made before the change. A change that claims "behaviour unchanged" must give the
same bytes here (the set covers RGB-D, stereo, monocular, VIO, lines, dynamic filtering, loop closing, new maps
and merges, dense tracking, the BA worker, on synthetic and real sequences).

    python scripts/same_trajectories.py record before.json      # on the old code
    python scripts/same_trajectories.py compare before.json     # on the new code: exit 1 on any difference

``--only NAME`` runs some cases; cases whose data is absent are skipped and said so.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

SYN_LOOP = ["dataset.synthetic.n_movers=0", "dataset.synthetic.loop=true"]
CASES: dict[str, tuple[str, list[str], str]] = {  # name -> (config, overrides, data under $VSLAM_DATA or "")
    "syn-rgbd": ("synthetic", [], ""),
    "syn-rgbd-lines": ("synthetic", ["slam.lines.enabled=true", "dataset.synthetic.n_frames=120"], ""),
    "syn-dynamic": ("synthetic_dynamic", [], ""),
    "syn-dynamic-detector": ("synthetic_dynamic", ["slam.dynamic.source=detector", "dataset.synthetic.n_frames=80"], ""),
    "syn-loop-closing": ("synthetic", SYN_LOOP + ["slam.loop.enabled=true"], ""),
    "syn-loop-async": ("synthetic_stereo", SYN_LOOP + ["slam.mapping.ba_lag_frames=10"], ""),
    "syn-kidnapped": ("synthetic", SYN_LOOP + ["dataset.synthetic.n_frames=280", "dataset.drop=[[60, 239]]"], ""),
    "syn-mono-loop": ("synthetic_mono", ["dataset.synthetic.loop=true", "slam.loop.enabled=true"], ""),
    "syn-vio": ("synthetic_vio", [], ""),
    "syn-vio-mono": ("synthetic_vio_mono", [], ""),
    "syn-dense": ("synthetic_corridor_dense", [], ""),
    "tum-rgbd": ("tum_rgbd", [], "tum/rgbd_dataset_freiburg3_teddy"),
    "tum-rgbd-gap": ("tum_rgbd", ["dataset.drop=[[60, 119]]"], "tum/rgbd_dataset_freiburg3_teddy"),
    "kitti-mono": ("kitti_mono", [], "kitti/sequences/07"),
    "euroc-stereo": ("euroc_stereo", [], "euroc/V1_01_easy_micro"),
    "euroc-vio": ("euroc_stereo_inertial", [], "euroc/V1_01_easy_micro"),
}
OUTPUTS = ("trajectory.tum.txt", "trajectory_final.tum.txt", "keyframes.tum.txt", "trajectory.kitti.txt", "map.ply",
           "map_lines.ply")


def _data_root() -> Path:
    env = os.environ.get("VSLAM_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"


def run_case(name: str, out: Path) -> dict[str, str] | str:
    config, sets, data = CASES[name]
    cmd = [sys.executable, "-m", "vslam.cli", "run", "-q", "--config", config, "-o", str(out), "--no-eval"]
    if data:
        d = _data_root() / data
        if not d.exists():
            return f"skipped: {d} absent"
        cmd += ["--data", str(d)]
    for s in sets:
        cmd += ["--set", s]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        return f"failed (exit {r.returncode}): {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ''}"
    return {f: hashlib.sha256((out / f).read_bytes()).hexdigest()[:16] for f in OUTPUTS if (out / f).is_file()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=["record", "compare"], help="write the hashes, or compare against them")
    ap.add_argument("file", help="the JSON record")
    ap.add_argument("--only", nargs="*", default=None, help="case names (default: all)")
    a = ap.parse_args()
    names = a.only or list(CASES)
    with tempfile.TemporaryDirectory() as tmp:
        got = {}
        for n in names:
            got[n] = run_case(n, Path(tmp) / n)
            print(f"{n}: {got[n] if isinstance(got[n], str) else 'ok'}", flush=True)
    if a.mode == "record":
        Path(a.file).write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
        return 0
    ref = json.loads(Path(a.file).read_text())
    bad = 0
    for n in names:
        if n not in ref:
            print(f"{n}: not in the record")
            continue
        if got[n] != ref[n]:
            bad += 1
            print(f"{n}: DIFFERENT\n  before {ref[n]}\n  now    {got[n]}")
    print("same bytes" if not bad else f"{bad} case(s) differ")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
