"""Kind ``sfm``: a monocular pipeline run measured against offline incremental SfM on the same frames.

The reference is COLMAP's incremental mapper (pycolmap): SIFT on every frame the run reads, sequential matching,
the calibrated camera held fixed, the largest model kept. Both trajectories are Sim3-aligned to the ground truth
with evo (``vslam.eval``) and the row reports vslam ATE / SfM ATE. The SfM result is cached under
``<jobs dir>/_sfm/<key>/`` (the key hashes the frame selection and the SfM settings), so a rerun of the bench only
runs the pipeline; a row that starts later in a recording maps from the whole recording's features and matches.

Row options go in ``set:`` beside the pipeline overrides, under ``sfm.`` (``SfmOptions``), e.g.
``sfm.overlap=10``, ``sfm.rel_lengths=[20, 40, 60, 80]``. Beyond the ATE ratio the row reports:

- ``t_rel`` / ``r_rel``: the KITTI odometry metric (% and deg / 100 m) over ``rel_lengths`` on the Sim3-aligned
  poses (the devkit scores the unaligned ones, meaningless without a metric scale), for both runs;
- ``scale_thirds``: the Sim3 scale of each third of the run (aligned alone) over the whole run's; ``scale_jump`` is
  the largest departure from 1 (a scale that drifts or jumps shows here long before it dominates the ATE).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vslam.bench.suite import BenchRow
from vslam.bench.tables import fmt, md_failed_row, md_section
from vslam.config import from_dict
from vslam.data.trajectory import Trajectory, read_trajectory, write_trajectory
from vslam.errors import ConfigError, EvalError

log = logging.getLogger(__name__)

CACHE_VERSION = 1  # bump when the way the reference is computed changes (a new key, old caches ignored)


@dataclass(frozen=True)
class SfmOptions:
    """The reference's settings (``sfm.<key>`` in a row's ``set:``) and the row's extra metrics."""

    overlap: int = 10  # sequential matching: each frame against the next ``overlap`` frames
    # ... and the frames 2^k ahead (COLMAP's default; off: docs/tracking.md, "Monocular against offline SfM")
    quadratic_overlap: bool = False
    max_features: int = 8192  # SIFT keypoints per frame
    threads: int = 2
    seed: int = 0
    # COLMAP's first pair: its least triangulation angle (deg) and largest forward share of the motion (defaults:
    # COLMAP's); a synthetic street driven straight ahead finds no pair under them
    init_min_tri_angle: float = 16.0
    init_max_forward_motion: float = 0.95
    # segment lengths (m) of t_rel / r_rel; empty: KITTI's 100..800 m
    rel_lengths: tuple[float, ...] = ()
    rel_step: int = 10  # frames between segment starts (KITTI devkit: 10)
    # the SfM model is a reference only if its own scale per third stays within this of its whole-run scale
    max_reference_jump: float = 0.1


def job(config: str | None, overrides: dict[str, Any], out_dir: str) -> dict[str, Any]:
    from vslam.bench.kinds.run import run_pipeline
    from vslam.pipeline import PipelineConfig

    overrides = dict(overrides)
    opts = from_dict(SfmOptions, overrides.pop("sfm", None) or {}, "sfm options")
    row, res = run_pipeline(config, overrides, out_dir)
    gt = res.eval_groundtruth
    if gt is None or res.eval is None:
        raise EvalError(f"sfm row: the run has no evaluation ({res.eval_skipped or 'no ground truth'})")
    cfg = PipelineConfig.load(config, overrides)
    lengths = opts.rel_lengths or cfg.eval.kitti_lengths
    ours = _scored_trajectory(res)
    row.update(_metrics(ours, gt, cfg.eval, lengths, opts.rel_step, "vslam"))
    ref, info = sfm_reference(cfg, opts, Path(out_dir).parent / "_sfm")
    row["sfm"] = info
    if len(ref) >= 3:
        row.update(_metrics(ref, gt, cfg.eval, lengths, opts.rel_step, "sfm"))
        row["sfm_ratio"] = row["ate_rmse"] / row["sfm_ate"] if row.get("sfm_ate") else None
    row["rel_lengths"] = list(lengths)
    return reference_check(row, opts.max_reference_jump)


def reference_check(row: dict[str, Any], max_jump: float) -> dict[str, Any]:
    """An SfM model whose own scale changes between thirds of the run by more than ``max_jump`` is no reference:
    its ratio is dropped (None) and ``sfm_invalid`` says why."""
    thirds = [x for x in row.get("sfm_scale_thirds") or [] if x is not None]
    jump = max(abs(x - 1.0) for x in thirds) if len(thirds) == 3 else None
    row["sfm_scale_jump"] = jump
    if row.get("sfm_ate") is not None and (jump is None or jump > max_jump):
        row["sfm_ratio"] = None
        row["sfm_invalid"] = (f"the SfM model's own scale per third is {', '.join(f'{x:.2f}' for x in thirds)} "
                              f"of its whole-run scale: not a reference")
    return row


def _scored_trajectory(res: Any) -> Trajectory:
    """The poses the run's own ATE scored: the main map when maps were never merged."""
    traj = res.trajectory
    if res.scored_map is not None and res.map_ids is not None:
        traj = traj.subset(np.flatnonzero(res.map_ids == res.scored_map))
    return traj


def _metrics(est: Trajectory, gt: Trajectory, eval_cfg: Any, lengths: tuple[float, ...], step: int,
             prefix: str) -> dict[str, Any]:
    """{prefix}_ate (Sim3), _t_rel / _r_rel on the aligned poses, _scale_thirds, and (vslam) scale_jump."""
    from vslam.eval.associate import associate
    from vslam.eval.kitti import kitti_odometry_error
    from vslam.eval.metrics import align, ate

    assoc = associate(est, gt, eval_cfg.max_diff)
    fit, gt_evo, est_evo = align(assoc, "sim3")
    out: dict[str, Any] = {f"{prefix}_ate": ate(gt_evo, est_evo)[0].translation.rmse, f"{prefix}_matched": len(assoc),
                           f"{prefix}_scale": fit.s}
    kitti, why = kitti_odometry_error(np.asarray(gt_evo.poses_se3), np.asarray(est_evo.poses_se3), tuple(lengths), step)
    out[f"{prefix}_t_rel"] = kitti.t_rel if kitti is not None else None
    out[f"{prefix}_r_rel"] = kitti.r_rel if kitti is not None else None
    if kitti is None:
        out[f"{prefix}_rel_note"] = why
    thirds = []
    for part in np.array_split(np.arange(len(assoc)), 3):
        if len(part) < 3:
            continue
        sub = type(assoc)(assoc.gt.subset(part), assoc.est.subset(part), assoc.by_index)
        try:
            thirds.append(align(sub, "sim3")[0].s / fit.s)
        except EvalError:
            thirds.append(None)
    out[f"{prefix}_scale_thirds"] = thirds
    if prefix == "vslam":
        ok = [abs(r - 1.0) for r in thirds if r is not None]
        out["scale_jump"] = max(ok) if len(ok) == 3 else None
    return out


# -- the offline reference ---------------------------------------------------------------------------------------

def sfm_reference(cfg: Any, opts: SfmOptions, cache_root: Path) -> tuple[Trajectory, dict[str, Any]]:
    """(T_world_cam of the frames SfM registered, info) for the frames ``cfg.dataset`` selects; cached.

    Features and matches live in a database of their own folder: a selection that starts later in the recording
    (``drop`` ranges from frame 0 only, stride 1) maps from the database of the whole recording restricted to its
    frames, which are the same features and the same sequential pairs it would make alone."""
    folder = cache_root / _key(cfg.dataset, opts)
    traj_path, info_path = folder / "trajectory.tum.txt", folder / "info.json"
    if traj_path.is_file() and info_path.is_file():
        info = json.loads(info_path.read_text())
        info["cached"] = True
        return read_trajectory(traj_path, "tum"), info
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    later_start = cfg.dataset.stride == 1 and cfg.dataset.drop and all(lo == 0 for lo, _ in cfg.dataset.drop)
    base = dataclasses.replace(cfg.dataset, drop=()) if later_start else cfg.dataset
    db_folder = cache_root / _key(base, opts, database=True)
    t0 = time.perf_counter()
    stamps = _database(base, opts, db_folder)
    names = [n for n in _names(cfg.dataset) if n in stamps]
    traj, info = _map(db_folder / "database.db", names, stamps, opts, folder)
    info["seconds"] = time.perf_counter() - t0
    info["database"] = db_folder.name
    write_trajectory(traj_path, traj, "tum")
    info_path.write_text(json.dumps(info, indent=1) + "\n")  # written last: its presence marks a complete cache
    info["cached"] = False
    return traj, info


_MAPPER_OPTIONS = ("init_min_tri_angle", "init_max_forward_motion")


def _key(dataset: Any, opts: SfmOptions, database: bool = False) -> str:
    """Cache folder name: the dataset's name and a hash of its non-default settings (the frame selection) and the
    SfM settings (not the metric options; mapper options only where not at their default, none for the features
    and matches: ``database``)."""
    import pycolmap

    from vslam.config import to_dict
    from vslam.data.config import DatasetConfig

    default = to_dict(DatasetConfig())
    ds = {k: v for k, v in to_dict(dataset).items() if v != default.get(k)}
    src = {"v": CACHE_VERSION, "pycolmap": pycolmap.__version__, "dataset": ds,
           "sfm": {k: v for k, v in dataclasses.asdict(opts).items()
                   if k not in ("rel_lengths", "rel_step", "max_reference_jump")
                   and not (k in _MAPPER_OPTIONS and (database or v == getattr(SfmOptions, k)))}}
    key = hashlib.sha1(json.dumps(src, sort_keys=True, default=str).encode()).hexdigest()[:12]
    return f"{Path(str(dataset.path or dataset.kind)).name}-{key}"


def _names(dataset: Any) -> list[str]:
    """Image names (``<frame index>.png``) of the frames the dataset config selects, in order."""
    from vslam.data.registry import open_dataset
    from vslam.data.select import kept_indices

    with open_dataset(dataset) as seq:
        idx = kept_indices(len(seq), dataset.stride, dataset.drop)
    if dataset.max_frames:
        idx = idx[: dataset.max_frames]
    return [f"{int(i):06d}.png" for i in idx]


def _camera_model(cam: Any) -> tuple[str, list[float]]:
    """COLMAP's model and parameters for our pinhole camera with its distortion."""
    base = [cam.fx, cam.fy, cam.cx, cam.cy]
    if not cam.is_distorted:
        return "PINHOLE", base
    d = list(cam.distortion)
    if cam.distortion_model == "equidistant":
        return "OPENCV_FISHEYE", base + (d + [0.0] * 4)[:4]
    if len(d) <= 4 or not any(d[4:]):
        return "OPENCV", base + (d + [0.0] * 4)[:4]
    return "FULL_OPENCV", base + (d + [0.0] * 8)[:8]


def _database(dataset: Any, opts: SfmOptions, folder: Path) -> dict[str, float]:
    """SIFT features and sequential matches of the frames ``dataset`` selects, in ``folder``/database.db (made
    once) -> {image name: timestamp}."""
    import cv2
    import pycolmap

    from vslam.data.registry import open_dataset
    from vslam.data.select import select_frames

    done = folder / "matched.json"
    if done.is_file():
        return json.loads(done.read_text())
    if (folder / "info.json").is_file() and (folder / "database.db").is_file():  # a complete run of these frames
        with open_dataset(dataset) as seq:
            t = seq.timestamps()
        stamps = {n: float(t[int(n[:6])]) for n in _names(dataset)}
        done.write_text(json.dumps(stamps) + "\n")
        return stamps
    folder.mkdir(parents=True, exist_ok=True)
    images = folder / "images"
    shutil.rmtree(images, ignore_errors=True)
    images.mkdir()
    stamps = {}
    with open_dataset(dataset) as base:
        seq = select_frames(base, dataset.stride, dataset.drop)
        cam = seq.calibration.cam0
        for n, frame in enumerate(seq):
            if dataset.max_frames and n >= dataset.max_frames:
                break
            name = f"{frame.index:06d}.png"
            cv2.imwrite(str(images / name), frame.image)
            stamps[name] = float(frame.timestamp)
    if not stamps:
        raise ConfigError("sfm row: the dataset selection holds no frame")
    model, params = _camera_model(cam)
    db = folder / "database.db"
    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model, reader.camera_params = model, ",".join(f"{p:.10g}" for p in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = opts.threads
    extraction.sift.max_num_features = opts.max_features
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap, pairing.quadratic_overlap, pairing.num_threads = opts.overlap, opts.quadratic_overlap, opts.threads
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    shutil.rmtree(images, ignore_errors=True)  # the mapper reads the database only (no colours)
    done.write_text(json.dumps(stamps) + "\n")
    return stamps


def _map(db: Path, names: list[str], stamps: dict[str, float], opts: SfmOptions,
         folder: Path) -> tuple[Trajectory, dict[str, Any]]:
    """COLMAP's incremental mapper on the images ``names`` of database ``db``, the camera held fixed; the
    largest model -> (T_world_cam by timestamp, info)."""
    import pycolmap

    mapper = pycolmap.IncrementalPipelineOptions()
    mapper.num_threads, mapper.random_seed = opts.threads, opts.seed
    mapper.mapper.random_seed = mapper.triangulation.random_seed = opts.seed
    mapper.ba_refine_focal_length = mapper.ba_refine_principal_point = mapper.ba_refine_extra_params = False
    mapper.extract_colors = False
    mapper.mapper.init_min_tri_angle = opts.init_min_tri_angle
    mapper.mapper.init_max_forward_motion = opts.init_max_forward_motion
    if len(names) < len(stamps):
        mapper.image_names = names
    models = pycolmap.incremental_mapping(db, folder, folder / "sparse", mapper)
    if not models:
        raise EvalError(f"sfm row: COLMAP registered no model from {len(names)} frames")
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    poses = []
    for img in rec.images.values():
        if not img.has_pose:
            continue
        T = np.eye(4)
        T[:3, :] = img.cam_from_world().inverse().matrix()
        poses.append((stamps[img.name], T))
    poses.sort(key=lambda p: p[0])
    rec.update_point_3d_errors()
    info = {"frames": len(names), "registered": len(poses), "models": len(models), "points": rec.num_points3D(),
            "reproj_px": rec.compute_mean_reprojection_error(), "camera": rec.cameras[1].model.name
            if 1 in rec.cameras else ""}
    return Trajectory(np.array([p[0] for p in poses]), np.array([p[1] for p in poses]).reshape(-1, 4, 4)), info


def table(rows: list[tuple[BenchRow, dict[str, Any]]]) -> list[str]:
    """vslam against offline SfM on the same frames."""
    if not rows:
        return []
    lines = md_section(
        "Monocular against offline SfM (`sfm`)",
        "The pipeline run and COLMAP's incremental SfM (pycolmap: SIFT, sequential matching, the calibrated camera "
        "fixed, largest model) on the same frames, both Sim3-aligned to the ground truth (evo). t_rel % / r_rel "
        "deg per 100 m: the KITTI metric on the aligned poses over the row's segment lengths. Scale per third: "
        "each third of the run aligned alone, its scale over the whole run's (1 = no drift or jump).",
        ["row", "frames (SfM registered)", "vslam ATE m", "SfM ATE m", "ratio", "t_rel / r_rel vslam",
         "t_rel / r_rel SfM", "segments m", "scale per third (vslam)", "ms/frame", "target"])
    for row, r in rows:
        if "error" in r:
            lines.append(md_failed_row(row, r["error"], 11))
            continue
        sfm = r.get("sfm") or {}
        thirds = ", ".join("–" if x is None else f"{x:.3f}" for x in r.get("vslam_scale_thirds") or [])
        segs = ", ".join(f"{x:g}" for x in r.get("rel_lengths") or [])
        lines.append(
            f"| {row.name} | {r.get('frames_read', r.get('frames'))} ({sfm.get('registered', '–')}) | "
            f"{fmt(r.get('ate_rmse'), '.4f')} | {fmt(r.get('sfm_ate'), '.4f')} | {_ratio(r)} | "
            f"{_rel(r, 'vslam')} | {_rel(r, 'sfm')} | {segs} | {thirds} | {fmt(r.get('ms_per_frame'), '.1f')} | "
            f"{row.target} |")
    return lines


def _ratio(r: dict[str, Any]) -> str:
    if r.get("sfm_invalid"):
        return f"– ({r['sfm_invalid']})"
    return f"**{fmt(r.get('sfm_ratio'), '.2f')}x**"


def _rel(r: dict[str, Any], prefix: str) -> str:
    t, rot = r.get(f"{prefix}_t_rel"), r.get(f"{prefix}_r_rel")
    return "–" if t is None else f"{t:.2f} % / {rot:.2f}°"
