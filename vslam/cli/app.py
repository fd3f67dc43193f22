"""`vslam` command line: a thin shell over the Python API.

Every user mistake surfaces as a VslamError and is printed as one line
(``vslam: error: <file>:<line>: <problem>``) with exit code 2; an output the
system cannot write (permissions, a full disk) is one line too. SIGTERM ends a
run as Ctrl-C does: what was written so far is kept, children are ended, one
line, exit 130 / 143. Anything else is a bug: one line and exit 1, the
traceback with ``-v``.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import logging
import signal
import sys
import traceback
from pathlib import Path
from typing import Any

from vslam import __version__
from vslam.errors import ConfigError, VslamError
from vslam.progress import progress_bar


def _summary(result: Any, out: Path) -> None:
    """What the run did, then what its number scores: with several maps the whole picture comes first and the
    headline ATE is labelled as the largest map's, so the line a reader copies says what it covers."""
    dropped = f", {result.dropped} dropped by the live queue" if getattr(result, "dropped", None) is not None else ""
    n, posed = result.n_frames, len(result.trajectory)
    unposed = f", {n - posed} without a pose" if posed < n else ""
    skipped = result.skipped
    if skipped:
        shown = ", ".join(map(str, skipped[:5])) + (", ..." if len(skipped) > 5 else "")
        unposed += f", {len(skipped)} skipped (did not decode: frame {shown})"
    print(f"frames: {n} read, {posed} posed ({int(result.tracked.sum())} tracked){unposed}; "
          f"{result.fps:.1f} frames/s{dropped}")
    if result.association is not None:  # the recording's pairing: what was used, what was dropped and why
        print(result.association.summary())
    rec = getattr(result, "recovery", {})
    if rec.get("new_maps"):  # tracking was lost: how the maps ended
        print(f"maps: {rec['new_maps']} new after tracking losses, {rec.get('merges', 0)} merged into older ones, "
              f"{rec.get('map_switches', 0)} taken up again by relocalisation; {len(result.maps_summary())} at the end")
    print(f"trajectory: {result.paths.get('trajectory_tum', out)}")
    if result.eval is None:
        print(f"not evaluated: {result.eval_skipped}" if result.eval_skipped else "no ground truth: trajectory not evaluated")
        return
    if result.scored_map is not None:  # tracking was lost and the maps never met: each is scored in its own frame
        maps = result.maps_summary()
        print(f"{len(maps)} maps, never merged; posed {posed} of {n} frames; each map aligned on its own:")
        for m in maps:
            e = result.map_evals.get(m["map"])
            score = "not scored (too few poses matched the ground truth)" if e is None else e.ate_text() + (
                f", {e.n_matched} matched to ground truth" if e.n_matched < m["poses"] else "")
            print(f"  map {m['map']}: {m['poses']} poses, {score}")
        main = next(m for m in maps if m["map"] == result.scored_map)
        print(f"largest map only (map {result.scored_map}, {main['poses']} of {n} frames): {result.eval.summary()}")
    else:
        print(result.eval.summary())
    for e in [result.eval, *result.map_evals.values()]:
        if e.scale_warning:
            print(f"warning: {e.scale_warning}")
            break
    if "report_html" in result.paths:
        print(f"report: {result.paths['report_html']}")


def _reclaim_sigterm() -> None:
    """pycolmap's import installs glog's failure handler for SIGTERM (a stack dump, no cleanup): once the
    pipeline's modules are imported, SIGTERM is ours again (``main``)."""
    if signal.getsignal(signal.SIGTERM) is _on_sigterm:
        signal.signal(signal.SIGTERM, _on_sigterm)


def _add_viewer_args(p: argparse.ArgumentParser) -> None:
    """--viewer / --rrd / --serve: watch the run in Rerun (output.viewer; docs/viewer.md)."""
    g = p.add_argument_group("viewer (Rerun, needs pip install 'vslam[viewer]'; docs/viewer.md)")
    g.add_argument("--viewer", action="store_true", help="start the Rerun viewer and stream the run to it")
    g.add_argument("--rrd", metavar="FILE", help="record the run to a Rerun file (open it with `rerun FILE`)")
    g.add_argument("--serve", action="store_true", help="serve the Rerun web viewer (address printed)")


def _viewer_overrides(args: argparse.Namespace) -> dict[str, Any]:
    v = {k: val for k, val in (("spawn", args.viewer), ("serve", args.serve), ("rrd", args.rrd)) if val}
    return {"output": {"viewer": v}} if v else {}


def _announce_viewer(cfg: Any) -> None:
    if cfg.output.viewer.serve:
        from vslam.viz.rerun_log import web_viewer_url

        print(f"Rerun web viewer: {web_viewer_url(cfg.output.viewer)}", flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    from vslam.config import deep_merge, parse_overrides
    from vslam.pipeline import Pipeline, PipelineConfig
    from vslam.resources import preset_path

    _reclaim_sigterm()

    over: dict[str, Any] = {}
    ds: dict[str, Any] = {}
    if args.data:
        ds["path"] = args.data
    if args.live is not None:  # a camera, stream or video read as it comes (vslam.data.live)
        if args.data or args.kind:
            raise ConfigError("--live names the input: give it without --data / --kind")
        ds.update(kind="live", path=args.live, sensor=args.sensor or "mono")
    if args.kind:
        ds["kind"] = args.kind
    if args.sensor:
        ds["sensor"] = args.sensor
    ds.update({k: v for k, v in (("camera", args.camera), ("times", args.times), ("fps", args.fps)) if v is not None})
    if args.max_frames is not None:
        if args.max_frames <= 0:
            raise ConfigError(f"--max-frames must be a positive number of frames, got {args.max_frames}")
        ds["max_frames"] = args.max_frames
    if ds:
        over["dataset"] = ds
    if args.out:
        over["output"] = {"dir": args.out}
    if args.no_eval:
        over["eval"] = {"enabled": False}
    over = deep_merge(deep_merge(over, _viewer_overrides(args)), parse_overrides(args.set or []))
    cfg = PipelineConfig.load(preset_path(args.preset) if args.preset else args.config, over)
    if args.data and not args.kind and cfg.dataset.kind == "synthetic":
        # --data names a folder: a config made for the built-in sequence then reads it by its layout. A config
        # made for one dataset kind keeps it, and a folder of another layout is an error (open_dataset).
        cfg = dataclasses.replace(cfg, dataset=dataclasses.replace(cfg.dataset, kind="auto"))
    _announce_viewer(cfg)
    with progress_bar("tracking", quiet=args.quiet) as bar:
        result = Pipeline(cfg).run(progress=bar)
    _summary(result, Path(cfg.output.dir))
    if result.error is not None:  # the outputs are written; what they lack (evaluation, a tracked pose) is an error
        raise result.error
    if args.profile:  # profiling: per-stage ms and peak memory, also written as profile.json
        from vslam.profiling import format_profile, write_profile

        print(format_profile(write_profile(result.paths["stats"], Path(cfg.output.dir) / "profile.json")))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from vslam.config import deep_merge
    from vslam.pipeline import Pipeline, PipelineConfig

    _reclaim_sigterm()

    cfg = PipelineConfig.load(None, deep_merge({"dataset": {"kind": "synthetic", "sensor": "rgbd", "max_frames": args.frames},
                                                "output": {"dir": args.out}}, _viewer_overrides(args)))
    print(f"vslam {__version__} demo: built-in synthetic room (RGB-D, 3 moving boxes, not masked yet), SLAM tracker")
    _announce_viewer(cfg)
    with progress_bar("demo", quiet=args.quiet) as bar:
        result = Pipeline(cfg).run(progress=bar)
    _summary(result, Path(args.out))
    return 0


def cmd_presets(args: argparse.Namespace) -> int:
    from vslam.resources import preset_description, preset_names, presets_dir

    names = preset_names()
    width = max(map(len, names))
    for name in names:
        print(f"{name:<{width}}  {preset_description(name)}")
    print(f"\n`vslam run --preset NAME`; to change one, copy it from {presets_dir()} and pass the copy with -c")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from vslam.eval import EvalConfig, evaluate_files, write_report

    cfg = EvalConfig(align=args.align, max_diff=args.max_diff)
    res = evaluate_files(args.est, args.gt, cfg, est_format=args.est_format, gt_format=args.gt_format, monocular=args.mono,
                         est_times=args.est_times, gt_times=args.gt_times)
    a = res.ate.translation
    scale = f", scale {res.alignment.s:.6f}" if res.alignment.method == "sim3" else ""
    print(f"ATE ({res.alignment.method}{scale}): rmse {a.rmse:.6f} m, mean {a.mean:.6f}, median {a.median:.6f}, max {a.max:.6f}, n {a.n}")
    for r in res.rpe:
        print(f"RPE {r.label}: trans rmse {r.translation.rmse:.6f} m, rot rmse {r.rotation_deg.rmse:.4f} deg")
    if res.kitti is not None:
        print(f"KITTI: t_rel {res.kitti.t_rel:.4f} %, r_rel {res.kitti.r_rel:.4f} deg/100m")
    elif res.kitti_reason:
        print(f"KITTI metric: n/a ({res.kitti_reason})")
    for note in res.notes:
        print(f"note: {note}")
    if args.out:
        paths = write_report(res, Path(args.out), title=f"vslam eval: {Path(args.est).name}")
        print(f"report: {paths['report_html']}")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from vslam.config import deep_merge, load_yaml, parse_overrides
    from vslam.config import from_dict
    from vslam.data.synthetic import SyntheticConfig, SyntheticSequence, write_sequence

    data: dict[str, Any] = load_yaml(args.config) if args.config else {}
    if "dataset" in data:  # accept a pipeline config and use its dataset.synthetic block
        data = (data.get("dataset") or {}).get("synthetic") or {}
    quick = {k: v for k, v in (("n_frames", args.frames), ("seed", args.seed), ("scene", args.scene)) if v is not None}
    data = deep_merge(deep_merge(data, quick), parse_overrides(args.set or []))
    scfg = from_dict(SyntheticConfig, data, args.config or "<synth>")
    paths = write_sequence(SyntheticSequence(scfg), Path(args.out))
    for k, p in paths.items():
        print(f"{k}: {p}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from vslam.bench import check_bench, render_bench, run_bench

    from vslam.bench.batch import parse_sweep

    sweep = parse_sweep(args.sweep) if args.sweep else None
    output = Path(args.output or ("runs/bench/sweep.md" if sweep else "BENCHMARKS.md"))
    if args.check:  # no runs: the targets on the sidecar as written
        lines, code = check_bench(args.suite, output)
        print("\n".join(lines))
        return code
    readme = None if sweep or args.readme == "" else Path(args.readme or output.parent / "README.md")
    if args.render:
        out = render_bench(args.suite, output, readme)
    else:
        with progress_bar("bench", unit="job", quiet=args.quiet) as bar:
            out = run_bench(args.suite, output, repeat=args.repeat, only=args.only, jobs_dir=Path(args.runs),
                            workers=args.jobs, ray=args.ray, sweep=sweep, readme=readme, progress=bar)
    print(f"wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vslam", description="Visual(-inertial) SLAM with honest evaluation.")
    p.add_argument("--version", action="version", version=f"vslam {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="-v info, -vv debug logging")
    p.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    sub = p.add_subparsers(dest="cmd", required=True)

    r = sub.add_parser("run", help="run on a dataset sequence (or the synthetic default)")
    which = r.add_mutually_exclusive_group()
    which.add_argument("--config", "-c", help="YAML config file, or a preset's name")
    which.add_argument("--preset", help="a shipped config by name (`vslam presets` lists them)")
    r.add_argument("--data", "-d", help="sequence folder (TUM, KITTI or EuRoC layout), image folder, video or ROS bag "
                                        "(docs/inputs.md); relative paths also tried under $VSLAM_DATA")
    r.add_argument("--live", metavar="SOURCE", help="live input: camera index (0), stream URL (rtsp://...), realsense[:SERIAL] "
                                                   "or a video file replayed at its rate; --camera gives the intrinsics")
    r.add_argument("--kind", choices=["auto", "tum", "kitti", "euroc", "synthetic", "images", "video", "bag"],
                   help="how to read --data (default: the config's; with --data, auto: detected from its layout)")
    r.add_argument("--camera", help="camera file (camera.yaml or ORB-SLAM3 settings) of an image folder, video or bag")
    r.add_argument("--times", help="frame times of an image folder or video: one timestamp per line")
    r.add_argument("--fps", type=float, help="frame rate of an image folder or video (times = index / fps)")
    r.add_argument("--sensor", choices=["rgbd", "stereo", "mono"],
                   help="which images the tracker uses: colour + depth, a stereo pair, or one camera (default: the config's)")
    r.add_argument("--max-frames", type=int, metavar="N", help="stop after the first N frames")
    r.add_argument("--out", "-o", help="output folder (default from config: runs/latest)")
    r.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field, e.g. odometry.n_features=2000")
    r.add_argument("--profile", action="store_true", help="print ms per stage and peak memory (also profile.json)")
    r.add_argument("--no-eval", action="store_true", help="do not read or evaluate the sequence's ground truth")
    _add_viewer_args(r)
    r.set_defaults(fn=cmd_run)

    d = sub.add_parser("demo", help="run the built-in synthetic sequence end to end")
    d.add_argument("--out", "-o", default="runs/demo", help="output folder (default: %(default)s)")
    d.add_argument("--frames", type=int, default=300, help="frames of the synthetic room to run (default: %(default)s)")
    _add_viewer_args(d)
    d.set_defaults(fn=cmd_demo)

    sub.add_parser("presets", help="list the shipped configs (presets) with what each runs").set_defaults(fn=cmd_presets)

    e = sub.add_parser("eval", help="ATE/RPE/KITTI metrics of an estimate against ground truth")
    e.add_argument("est", help="the estimated trajectory (TUM, KITTI or EuRoC file)")
    e.add_argument("gt", help="the ground-truth trajectory (TUM, KITTI or EuRoC file)")
    e.add_argument("--est-format", default="auto", choices=["auto", "tum", "kitti", "euroc"],
                   help="file format of the estimate (default auto: guessed from the file)")
    e.add_argument("--gt-format", default="auto", choices=["auto", "tum", "kitti", "euroc"],
                   help="file format of the ground truth (default auto: guessed from the file)")
    e.add_argument("--align", default="auto", choices=["auto", "se3", "sim3", "none"],
                   help="alignment of the estimate to the ground truth before scoring (default auto: sim3 with --mono, "
                        "else se3)")
    e.add_argument("--mono", action="store_true", help="monocular estimate: auto alignment becomes Sim3")
    e.add_argument("--max-diff", type=float, default=0.02, help="timestamp association tolerance, seconds")
    e.add_argument("--times", "--est-times", dest="est_times", metavar="FILE",
                   help="timestamps of a KITTI-format estimate (one per line, as KITTI's times.txt)")
    e.add_argument("--gt-times", metavar="FILE", help="timestamps of a KITTI-format ground truth")
    e.add_argument("--out", "-o", help="write report.md/report.html/metrics.json/plots here")
    e.set_defaults(fn=cmd_eval)

    s = sub.add_parser("synth", help="write a synthetic sequence in TUM and EuRoC layouts")
    s.add_argument("out", help="output folder (rgbd/ in the TUM layout, mav0/ in the EuRoC one)")
    s.add_argument("--config", "-c", help="YAML with SyntheticConfig fields (or a pipeline config)")
    s.add_argument("--frames", type=int, metavar="N", help="number of frames (default: the config's, else 300)")
    s.add_argument("--seed", type=int, help="random seed of the scene, its textures and movers (default: the config's, else 0)")
    s.add_argument("--scene", choices=["room", "street", "corridor"], help="the world to render (default: the config's, else room)")
    s.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a SyntheticConfig field, e.g. n_movers=0 (repeatable)")
    s.set_defaults(fn=cmd_synth)

    b = sub.add_parser("bench", help="run the benchmark suite and rewrite BENCHMARKS.md")
    b.add_argument("--suite", default="configs/bench.yaml", help="YAML listing the rows and their targets (default: %(default)s)")
    b.add_argument("--output", default=None, help="default BENCHMARKS.md (with --sweep: runs/bench/sweep.md)")
    b.add_argument("--runs", default="runs/bench", help="where each job's outputs go")
    b.add_argument("--repeat", type=int, default=1, help="runs per row (median and spread reported)")
    b.add_argument("--only", action="append", help="run only rows with this name (repeatable)")
    b.add_argument("--jobs", type=int, default=1, help="jobs at a time over a local process pool (timings then share the cores)")
    b.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS",
                   help="run the jobs as Ray tasks: on the cluster at ADDRESS, or a local Ray instance of --jobs CPUs")
    b.add_argument("--sweep", action="append", metavar="KEY=V1,V2", help="run each selected row once per value (repeatable: a grid)")
    mode = b.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true",
                      help="run nothing: check every row's targets on BENCHMARKS.json as written; exit 1 on a miss not marked open")
    mode.add_argument("--render", action="store_true",
                      help="run nothing: rewrite BENCHMARKS.md and the README's results table from BENCHMARKS.json")
    b.add_argument("--readme", default=None, metavar="FILE",
                   help="README whose bench-table markers get the headline rows (default: README.md beside --output; '' for none)")
    b.set_defaults(fn=cmd_bench)
    from vslam.cli import dynamic, features, fusion, train

    fusion.add_cli(sub)
    train.add_cli(sub.add_parser("train", help="train a network (detector, place, keypoints)").add_subparsers(
        dest="model", required=True))
    features.add_cli(sub)
    # `vslam quantize <model>`: int8 ranges of a network for CPU inference (vslam.quantize)
    features.add_quantize_cli(sub.add_parser("quantize", help="calibrate int8 CPU inference of a network "
                                             "(keypoints)").add_subparsers(dest="model", required=True))
    dynamic.add_cli(sub)
    _add_quiet(p)
    return p


QUIET_HELP = "no progress bar (one shows on stderr only when it is a terminal; VSLAM_PROGRESS=0 also turns it off)"


def _add_quiet(parser: argparse.ArgumentParser) -> None:
    """-q after any subcommand too (``vslam run -q`` as well as ``vslam -q run``), also on those that other modules
    add. SUPPRESS: a subcommand given no -q leaves the value parsed before it."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sp in {id(sp): sp for sp in action.choices.values()}.values():  # an alias names the same parser
                sp.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
                _add_quiet(sp)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Python next runs: the same unwinding as Ctrl-C (outputs flushed, children ended)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise Terminated


def _os_error_line(e: OSError) -> str:
    where = f"{e.filename}: " if e.filename else ""
    why = e.strerror or str(e)
    if e.errno == errno.ENOSPC:
        why += " (outputs written so far are kept; files not yet written are missing)"
    return f"{where}{why}"


def main(argv: list[str] | None = None) -> int:
    interrupted: list[bool] = []  # Ctrl-C seen, even where a library turned it into another exception or ate it
    sigint = _watch_sigint(interrupted)
    try:
        return _main(argv, interrupted)
    finally:
        if sigint is not None:
            # after a Ctrl-C the process is ending with 130: a second one still pending in the interpreter (a
            # signal taken while C code held the thread is run later) must not kill it with a traceback
            signal.signal(signal.SIGINT, signal.SIG_IGN if interrupted else sigint)


def _call(args: argparse.Namespace, interrupted: list[bool]) -> int:
    """``args.fn(args)``; a Ctrl-C that a library turned into its own error (an import interrupted half way: an
    ImportError) or caught is raised again as the KeyboardInterrupt it was."""
    try:
        code = args.fn(args)
    except Exception:
        if interrupted:
            raise KeyboardInterrupt from None
        raise
    if interrupted:
        raise KeyboardInterrupt
    return code


def _main(argv: list[str] | None, interrupted: list[bool]) -> int:
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        args = None
    if args is None or interrupted:  # a Ctrl-C while the subcommands' modules load, whatever caught it
        print("vslam: interrupted", file=sys.stderr)
        return 130
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.captureWarnings(True)
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (main() called from a thread): leave SIGTERM as it is
        previous = None
    try:
        return _call(args, interrupted)
    except VslamError as e:
        print(f"vslam: error: {e}", file=sys.stderr)
        return 2
    except Terminated:
        print("vslam: terminated (outputs written so far are kept)", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("vslam: interrupted (outputs written so far are kept)", file=sys.stderr)
        return 130
    except OSError as e:  # an output that cannot be written, a device that fails: the system's words, one line
        print(f"vslam: error: {_os_error_line(e)}", file=sys.stderr)
        return 2
    except Exception as e:  # a bug, not a user mistake: say so in one line; -v shows where
        if args.verbose:
            traceback.print_exc()
        print(f"vslam: internal error: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''} "
              "(a bug: please report it with the command; -v prints the traceback)", file=sys.stderr)
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _watch_sigint(seen: list[bool]) -> Any:
    """SIGINT raises KeyboardInterrupt as Python's own handler does, and is remembered in ``seen``: a Ctrl-C that
    lands inside an import can surface as an ImportError, which must still end as an interrupt. Returns the
    previous handler (None: not the main thread, nothing changed)."""
    def on_sigint(signum: int, frame: Any) -> None:
        seen.append(True)
        raise KeyboardInterrupt

    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:  # ignored (`cmd &`) or the caller's own
        return None
    try:
        return signal.signal(signal.SIGINT, on_sigint)
    except ValueError:
        return None

