"""``vslam train detector``: argparse wiring only (torch is imported when the command runs)."""

from __future__ import annotations

import argparse
import json

from vslam.train_cli import add_train_parser, train_config


def add_cli(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "detector", "train the attention detector (COCO128 + synthetic frames)", "TrainConfig",
                     "attention=cbam", "checkpoints, model.pt, metrics.json", cmd_train_detector)


def cmd_train_detector(args: argparse.Namespace) -> int:
    from vslam.dynamic.train import TrainConfig, train
    from vslam.progress import progress_bar

    with progress_bar("training", unit="it", quiet=args.quiet) as bar:
        metrics = train(train_config(TrainConfig, args), progress=bar)
    if metrics:  # under torchrun only rank 0 evaluates
        print(json.dumps(metrics, indent=2))
    return 0
