"""The options every ``vslam train <model>`` command shares (argparse only: torch is imported when one runs)."""

from __future__ import annotations

import argparse
from typing import Any, Callable


def add_train_parser(train_sub: argparse._SubParsersAction, name: str, help: str, config_cls: str, set_example: str,
                     outputs: str, fn: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    """``vslam train NAME`` with --config/--set/--out/--toy/--resume/--device; ``fn(args)`` runs it."""
    p = train_sub.add_parser(name, help=help)
    p.add_argument("--config", "-c", help=f"YAML with {config_cls} fields")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help=f"override a field, e.g. {set_example}")
    p.add_argument("--out", "-o", help=f"output folder ({outputs})")
    p.add_argument("--toy", action="store_true", help="tiny CPU smoke run of the whole recipe")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], help="where to train (default: the config's; auto: CUDA when there is one)")
    p.set_defaults(fn=fn)
    return p


def train_config(cls: type, args: argparse.Namespace) -> Any:
    """The trainer's config from --config plus --set, --out, --device, --toy, --resume."""
    from vslam.config import load_config, parse_overrides

    over = parse_overrides(args.set or [])
    for key, val in (("out", args.out), ("device", args.device)):
        if val is not None:
            over[key] = val
    if args.toy:
        over["toy"] = True
    if args.resume:
        over["resume"] = True
    return load_config(cls, args.config, over)
