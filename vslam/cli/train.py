"""``vslam train <model>``: detector, convert-yolox, keypoints, place, yolox, yolox-masks. The options every trainer
shares, and each trainer's command over its library ``train`` (argparse only: torch is imported when one runs)."""

from __future__ import annotations

import argparse
import json
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


def run_trainer(args: argparse.Namespace, config_cls: type, train: Callable[..., Any], unit: str) -> Any:
    """``train`` on the config from the command line (``train_config``), with a progress bar counting ``unit``
    -> what it returns (its metrics)."""
    from vslam.progress import progress_bar

    with progress_bar("training", unit=unit, quiet=args.quiet) as bar:
        return train(train_config(config_cls, args), progress=bar)


def add_cli(train_sub: argparse._SubParsersAction) -> None:
    _add_detector(train_sub)
    _add_place(train_sub)
    _add_keypoints(train_sub)
    _add_yolox(train_sub)
    _add_yolox_masks(train_sub)


def _add_detector(train_sub: argparse._SubParsersAction) -> None:
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
    from vslam.train.detector import TrainConfig, train

    metrics = run_trainer(args, TrainConfig, train, "it")
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


def _add_place(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "place", "train the VLADNet place descriptor (synthetic routes + KITTI + COCO + TUM)",
                     "PlaceTrainConfig", "steps=3000", "last.pt, model.pt, metrics.json", cmd_train_place)


def cmd_train_place(args: argparse.Namespace) -> int:
    from vslam.train.place import PlaceTrainConfig, train

    metrics = run_trainer(args, PlaceTrainConfig, train, "step")
    if metrics:  # under torchrun only rank 0 evaluates
        print(json.dumps(metrics["eval"], indent=2))
    return 0


def _add_keypoints(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "keypoints", "train ConvPoint (synthetic shapes -> homographic adaptation -> joint)",
                     "KeypointTrainConfig", "joint_steps=5000", "last.pt, pseudo.npz, model.pt, metrics.json", cmd_train_keypoints)


def cmd_train_keypoints(args: argparse.Namespace) -> int:
    from vslam.train.keypoints import KeypointTrainConfig, train

    metrics = run_trainer(args, KeypointTrainConfig, train, "step")
    if metrics:
        print(json.dumps({k: metrics[k] for k in ("loss", "stage_s") if k in metrics} | {"eval": metrics.get("eval")}, indent=2))
    return 0


def _add_yolox_masks(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "yolox-masks", "train the box-prompted mask head over the frozen YOLOX detector "
                     "(exact masks + BlazePose-lite pseudo-masks)", "MaskTrainConfig", "iterations=2000",
                     "last.pt, model.pt, log.csv, metrics.json", cmd_train_yolox_masks)


def cmd_train_yolox_masks(args: argparse.Namespace) -> int:
    from vslam.train.yolox_masks import MaskTrainConfig, train

    metrics = run_trainer(args, MaskTrainConfig, train, "it")
    print(json.dumps(metrics, indent=2))
    return 0


def _add_yolox(train_sub: argparse._SubParsersAction) -> None:
    add_train_parser(train_sub, "yolox", "fine-tune the YOLOX-style detector from the converted public weights (CPU)",
                     "YoloxTrainConfig", "iterations=600", "last.pt, model.pt, log.csv, metrics.json", cmd_train_yolox)


def cmd_train_yolox(args: argparse.Namespace) -> int:
    from vslam.train.yolox import YoloxTrainConfig, train

    metrics = run_trainer(args, YoloxTrainConfig, train, "it")
    print(json.dumps(metrics, indent=2))
    return 0
