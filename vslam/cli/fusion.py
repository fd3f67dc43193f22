"""``vslam fusion <experiment>``: the navigation-fusion experiments (``vslam.fusion.experiments``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from vslam.errors import ConfigError
from vslam.fusion.experiments import EXPERIMENTS


def cmd_fusion(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path("runs") / "fusion" / args.experiment
    extra = {}
    if args.vo_run:
        if args.experiment != "validity_vslam":
            raise ConfigError("--vo-run only applies to the validity_vslam experiment")
        extra["run_dir"] = args.vo_run
    metrics = EXPERIMENTS[args.experiment](out, seed=args.seed, quick=args.quick, **extra)
    print(json.dumps({"seed_claim": metrics.get("seed_claim"), "report": str(out / "report.md")}, indent=2))
    return 0


def add_cli(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``fusion <experiment>`` on an argparse subparsers object (handler in ``fn``)."""
    p = subparsers.add_parser("fusion", help="navigation-fusion experiments (seeds 000, 002, 003 ch. 2, 004)")
    p.add_argument("experiment", choices=sorted(EXPERIMENTS), help="which experiment to run (docs/fusion.md)")
    p.add_argument("--out", default=None, help="output folder (default runs/fusion/<experiment>)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated runs and sensor noise (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="small, fast version (for tests and smoke runs)")
    p.add_argument("--vo-run", default=None, metavar="DIR",
                   help="validity_vslam: a `vslam run` output folder whose trajectory is the VIO channel "
                        "(default: run vslam on KITTI 07 mono, or the synthetic street without the data)")
    p.set_defaults(fn=cmd_fusion)
    return p
