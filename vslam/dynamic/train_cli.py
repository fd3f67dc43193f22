"""``vslam train detector``: argparse wiring only (torch is imported when the command runs)."""

from __future__ import annotations

import argparse
import json


def add_cli(train_sub: argparse._SubParsersAction) -> None:
    d = train_sub.add_parser("detector", help="train the attention detector (COCO128 + synthetic frames)")
    d.add_argument("--config", "-c", help="YAML with TrainConfig fields")
    d.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a field, e.g. attention=cbam")
    d.add_argument("--out", "-o", help="output folder (checkpoints, model.pt, metrics.json)")
    d.add_argument("--toy", action="store_true", help="tiny CPU smoke run of the whole recipe")
    d.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    d.add_argument("--device", choices=["auto", "cpu", "cuda"])
    d.set_defaults(fn=cmd_train_detector)


def cmd_train_detector(args: argparse.Namespace) -> int:
    from vslam.config import load_config, parse_overrides
    from vslam.dynamic.train import TrainConfig, train

    over = parse_overrides(args.set or [])
    for key, val in (("out", args.out), ("device", args.device)):
        if val is not None:
            over[key] = val
    if args.toy:
        over["toy"] = True
    if args.resume:
        over["resume"] = True
    metrics = train(load_config(TrainConfig, args.config, over))
    if metrics:  # under torchrun only rank 0 evaluates
        print(json.dumps(metrics, indent=2))
    return 0
