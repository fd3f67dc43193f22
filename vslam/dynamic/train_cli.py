"""``vslam train detector``: argparse wiring only (torch is imported when the command runs)."""

from __future__ import annotations

import argparse
import json

from vslam.train_cli import add_train_parser, train_config


def add_cli(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "detector", "train the attention detector (COCO128 + synthetic frames)", "TrainConfig",
                     "attention=cbam", "checkpoints, model.pt, metrics.json", cmd_train_detector)
    c = train_sub.add_parser("convert-yolox", help="convert the public YOLOX-nano (COCO) into our detector checkpoint")
    c.add_argument("--source", default="", help="the YOLOX-nano ONNX file (default: the shared data's "
                                                 "pretrained/yolox_nano/yolox_nano.onnx)")
    c.add_argument("--out", "-o", default="", help="checkpoint to write (default: the shipped "
                                                    "vslam/models/yolox_nano_slam.pt of this source tree)")
    c.add_argument("--classes", default="", help="comma-separated COCO class names to keep (default: person, "
                                                 "bicycle, car, motorcycle, bus, truck)")
    c.add_argument("--attention", default="none", choices=["none", "se", "cbam", "esea"],
                   help="attention blocks at the neck outputs, zero-gated (the outputs stay the source's)")
    c.add_argument("--float16", action="store_true", help="store float16 weights (half the size; probabilities move "
                                                          "by up to ~1e-2, default float32: the source's outputs)")
    c.set_defaults(fn=cmd_convert_yolox)


def cmd_train_detector(args: argparse.Namespace) -> int:
    from vslam.dynamic.train import TrainConfig, train
    from vslam.progress import progress_bar

    with progress_bar("training", unit="it", quiet=args.quiet) as bar:
        metrics = train(train_config(TrainConfig, args), progress=bar)
    if metrics:  # under torchrun only rank 0 evaluates
        print(json.dumps(metrics, indent=2))
    return 0


def cmd_convert_yolox(args: argparse.Namespace) -> int:
    from pathlib import Path

    from vslam.nn.weights.yolox import convert_to_file

    out = Path(args.out) if args.out else Path(__file__).resolve().parents[1] / "models" / "yolox_nano_slam.pt"
    classes = tuple(c.strip() for c in args.classes.split(",") if c.strip()) or None
    path, meta = convert_to_file(out, args.source or None, classes, args.attention, half=args.float16)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB, {meta['dtype']}, classes {', '.join(meta['classes'])}; "
          f"largest probability change from the stored precision {meta['max_abs_diff_stored']:.1e})")
    return 0
