"""``vslam make-dynamic``, ``vslam detect``, ``vslam eval-detector``: argparse and printing over the library functions
of ``vslam.dynamic`` (composite, detect, eval_detector)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vslam.errors import ConfigError


def add_cli(sub: argparse._SubParsersAction) -> None:
    _add_make_dynamic(sub)
    _add_eval_detector(sub)
    _add_detect(sub)


def add_detector_args(p: argparse.ArgumentParser, model_help: str, threshold_help: str) -> None:
    """The options every command that runs a detector shares: --model, --threshold, --img-size, --wide, --threads."""
    p.add_argument("--model", default="", help=model_help)
    p.add_argument("--threshold", type=float, help=threshold_help)
    p.add_argument("--img-size", type=int, default=0, help="network input size, the longer side, a multiple of 32 "
                                                             "(0 = the size the model was made for, as slam.dynamic.img_size)")
    p.add_argument("--wide", action="store_true", help="YOLOX-style detectors: keep the image's aspect (--img-size "
                                                      "its longer side) instead of a square input")
    p.add_argument("--threads", type=int, default=2, help="CPU threads of the network")


def checked_threshold(value: float | None, default: float) -> float:
    """--threshold, or ``default`` when not given; one line when it is not a score."""
    threshold = default if value is None else value
    if not 0 <= threshold <= 1:
        raise ConfigError(f"--threshold is a score in [0, 1], got {threshold}")
    return threshold


def _add_make_dynamic(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("make-dynamic", help="composite walking COCO people into a TUM RGB-D or KITTI sequence (+ masks)")
    m.add_argument("data", help="TUM RGB-D sequence folder (undistorted camera, e.g. freiburg3) or KITTI sequence "
                   "folder with poses; relative paths also under $VSLAM_DATA")
    m.add_argument("out", help="output folder (the input's layout + masks + boxes.txt)")
    m.add_argument("--coco", default="coco128", help="COCO128 folder with segments/ (relative: under $VSLAM_DATA)")
    m.add_argument("--people", type=int, help="walkers (default 3 for TUM, 6 spread along a KITTI drive)")
    m.add_argument("--seed", type=int, default=0, help="random seed of the walkers: which people, where and how they walk (default: %(default)s)")
    m.add_argument("--max-frames", type=int, metavar="N", help="composite only the first N frames")
    m.set_defaults(fn=cmd_make_dynamic)


def cmd_make_dynamic(args: argparse.Namespace) -> int:
    from vslam.data.composite import make_dynamic, walker_config
    from vslam.paths import data_root

    def find(p: str) -> Path:
        return Path(p) if Path(p).exists() or Path(p).is_absolute() else data_root() / p

    from vslam.progress import progress_bar

    with progress_bar("compositing", quiet=args.quiet) as bar:
        out = make_dynamic(find(args.data), args.out, find(args.coco),
                           walker_config(find(args.data), args.people, args.seed, args.max_frames), bar)
    print(f"wrote {out}")
    return 0


def _add_eval_detector(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("eval-detector", help="AP, recall at the SLAM threshold and mask IoU of a detector on a labelled folder")
    e.add_argument("data", help="folder in YOLO (COCO128), PASCAL (Penn-Fudan) or KITTI-object layout (auto-detected); "
                                "relative paths also tried under $VSLAM_DATA")
    e.add_argument("--split", default="val", choices=["val", "train", "all"], help="the fixed split (docs/detector-data.md)")
    add_detector_args(e, "detector checkpoint (default the shipped one); with --teacher an ONNX file",
                      "score threshold of recall / precision / mask IoU (default: SLAM's "
                      "slam.dynamic.score_threshold; 0.5 for --teacher)")
    e.add_argument("--teacher", action="store_true", help="evaluate FastestDet through onnxruntime (extra vslam[teacher])")
    e.add_argument("--json", help="also write the report as JSON here")
    e.set_defaults(fn=cmd_eval_detector)


def cmd_eval_detector(args: argparse.Namespace) -> int:
    import json

    from vslam.eval.detector import build_detector, evaluate, format_report, predict
    from vslam.paths import data_root
    from vslam.progress import progress_bar
    from vslam.train.photos import Split, load_records

    data = Path(args.data)
    if not data.exists() and not data.is_absolute() and (data_root() / data).exists():
        data = data_root() / data
    split: Split = args.split
    layout, records = load_records(data, split)
    det, slam_threshold, name = build_detector(args.model, args.teacher, args.threads, args.img_size, args.wide)
    threshold = checked_threshold(args.threshold, slam_threshold)
    with progress_bar("detecting", len(records), unit="image", quiet=args.quiet) as bar:
        preds = predict(det, records, bar)
    rep = evaluate(records, preds, threshold)
    rep.update(model=name, data=str(data), layout=layout, split=split)
    print(f"{name} on {data} ({layout}, split {split}, {len(records)} images)")
    print("\n".join(format_report(rep, name)))
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=2) + "\n")
    return 0


def _add_detect(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("detect", help="detect people and vehicles on images; write COCO-format results (JSON)")
    d.add_argument("images", nargs="+", help="image files or folders of images")
    d.add_argument("--out", "-o", required=True, help="JSON file to write (a list of COCO result entries)")
    add_detector_args(d, "detector checkpoint, either format (default: the shipped YOLOX-nano, the most accurate "
                         "on photos; SLAM's default is slam.dynamic.weights)",
                      "keep detections scoring at least this (default: SLAM's slam.dynamic.score_threshold)")
    d.set_defaults(fn=cmd_detect)


def cmd_detect(args: argparse.Namespace) -> int:
    import json

    from vslam.dynamic.config import DynamicConfig
    from vslam.eval.detect import coco_results, image_files
    from vslam.eval.detector import build_detector
    from vslam.progress import progress_bar

    threshold = checked_threshold(args.threshold, DynamicConfig().score_threshold)
    files = image_files(args.images)
    from vslam.dynamic.detector import photo_weights

    det, _, name = build_detector(args.model or str(photo_weights()), False, args.threads, args.img_size, args.wide)
    det.conf = min(det.conf, threshold)
    with progress_bar("detecting", len(files), unit="image", quiet=args.quiet) as bar:
        res = coco_results(det, files, threshold, bar)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res) + "\n")
    print(f"{name}: {len(res)} detections on {len(files)} images -> {args.out}")
    return 0
