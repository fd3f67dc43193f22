"""``vslam eval-features``: the feature benchmark (``eval.keypoints``) from the command line."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_cli(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval-features", help="ConvPoint vs ORB vs SIFT: homography benchmark + epipolar inliers on held-out frames")
    p.add_argument("--weights", default="", help="ConvPoint weights (default vslam/models/convpoint_v1.pt)")
    p.add_argument("--keypoints", type=int, default=1000, help="keypoints per image and method")
    p.add_argument("--pairs", type=int, default=2, help="random homographies per held-out image")
    p.add_argument("--images", type=int, default=12, help="held-out images per source")
    p.add_argument("--methods", default="orb,sift,convpoint,convpoint-int8", help="comma-separated methods to compare "
                   "(default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the homographies and illumination changes (default: %(default)s)")
    p.add_argument("--out", "-o", help="write results.json and table.md here")
    p.set_defaults(fn=_cmd)


def add_quantize_cli(quantize_sub: argparse._SubParsersAction) -> None:
    p = quantize_sub.add_parser("keypoints", help="int8 activation ranges of ConvPoint from training images (features.int8)")
    p.add_argument("--weights", default="", help="ConvPoint weights (default vslam/models/convpoint_v1.pt); ranges go beside them")
    p.add_argument("--per-source", type=int, default=8, help="training images per source (COCO128, TUM, KITTI, EuRoC)")
    p.set_defaults(fn=_cmd_quantize)


def _cmd_quantize(args: argparse.Namespace) -> int:
    import torch

    from vslam.features.convpoint import default_weights
    from vslam.paths import data_root
    from vslam.train.keypoints import calibrate_convpoint

    torch.set_num_threads(2)
    out = calibrate_convpoint(args.weights or default_weights(), data_root(), args.per_source)
    print(f"wrote {out}")
    return 0


def _cmd(args: argparse.Namespace) -> int:
    import torch

    from vslam.eval.keypoints import FeatureBenchConfig, format_table, run_feature_bench
    from vslam.features.convpoint import default_weights
    from vslam.paths import data_root
    from vslam.progress import progress_bar

    torch.set_num_threads(2)
    cfg = FeatureBenchConfig(n_keypoints=args.keypoints, pairs_per_image=args.pairs, max_images_per_source=args.images,
                             seed=args.seed)
    with progress_bar("evaluating", unit="pass", quiet=args.quiet) as bar:
        res = run_feature_bench(args.weights or default_weights(), data_root(), cfg, tuple(args.methods.split(",")), bar)
    table = "\n".join(format_table(res))
    print(table)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps(res, indent=2))
        (out / "table.md").write_text(table + "\n")
    return 0
