"""Entry point of the fusion experiments: ``EXPERIMENTS[name](out_dir, seed, quick) -> metrics``.

Each writes PNG plots, ``report.md`` and ``metrics.json`` into out_dir and returns the
headline metrics (JSON-safe, with 'seed_claim' and 'ours'). ``add_cli`` registers
``vslam fusion <experiment> [--out DIR] [--seed N] [--quick]``.
"""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path
from typing import Any, Callable

from vslam.errors import ConfigError

Experiment = Callable[..., dict[str, Any]]


def _lazy(module: str, name: str) -> Experiment:
    """The experiment ``module.name``, imported when first called: the experiment modules pull in scipy.stats and
    matplotlib (~0.6 s), which every other ``vslam`` command would otherwise pay at start (the CLI registers
    ``fusion`` with the rest)."""

    def run(*args: Any, **kwargs: Any) -> dict[str, Any]:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    run.__name__ = run.__qualname__ = name
    return run


EXPERIMENTS: dict[str, Experiment] = {
    "ins_gnss": _lazy("vslam.fusion.exp_nav", "run_ins_gnss"),
    "validity": _lazy("vslam.fusion.exp_nav", "run_validity"),
    # the same mode choice, VIO channel = a real vslam trajectory
    "validity_vslam": _lazy("vslam.fusion.exp_vslam", "run_validity_vslam"),
    "identification": _lazy("vslam.fusion.exp_group", "run_identification"),
    "multi_vehicle": _lazy("vslam.fusion.exp_group", "run_multi_vehicle"),
}


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
