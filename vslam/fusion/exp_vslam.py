"""The GNSS-blocked mode switch (seed 000 eqs. 11-12) on a simulated drive that follows a real
vslam run: the drive is the ground truth of a vslam sequence, turned into the INS/GNSS simulator's truth
(``simulate.truth_from_samples``); the VIO channel is vslam's own estimate of that sequence.

Default sequence: KITTI 07 frames 0-159, monocular (``configs/kitti_mono.yaml``; 90 m in 16 s), from
$VSLAM_DATA; the synthetic street (RGB-D, 50 m in 10 s) when the real data are absent. GNSS runs at the
camera rate (10 Hz) because the drive is short; it is fully blocked over the middle 40 % of the drive.
The vslam track lives in its own frame (and scale, monocular): it is aligned to the GNSS/INS solution over
the valid epochs before the blockage (``exp_nav.align_to_nav``), never to the ground truth.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vslam.data.trajectory import Trajectory, read_trajectory
from vslam.errors import ConfigError
from vslam.fusion.exp_nav import run_validity
from vslam.fusion.ins_gnss import InsGnssConfig
from vslam.fusion.simulate import GnssConfig, ImuConfig, TrajectoryConfig, Truth, truth_from_samples

log = logging.getLogger(__name__)

# vslam's world is its first camera (x right, y down, z forward); the navigation frame is (North, Up, East):
# North = forward, Up = -y, East = right at the start of the drive.
R_NAV_WORLD = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
# body axes (forward, up, right) in camera coordinates, as columns: C_b^n = R_nav_world R_world_cam R_cam_body
R_CAM_BODY = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


# Whether the visual modes pay off over a short blockage depends on how fast the INS drifts, so the drive is
# simulated with two grades: the tactical/MEMS unit of the other experiments and an automotive MEMS unit
# (20 mg accel bias, ~100 deg/h gyro bias).
IMU_GRADES: dict[str, ImuConfig] = {
    "tactical": ImuConfig(),
    "automotive": ImuConfig(accel_bias=0.2, gyro_bias=5e-4, accel_noise=0.05, gyro_noise=5e-4,
                            accel_bias_rw=5e-4, gyro_bias_rw=1e-5),
}


@dataclass(frozen=True)
class VslamValidityConfig:
    """Which vslam run feeds the VIO channel, and the simulated sensors around its drive."""

    config: str = "configs/kitti_mono.yaml"  # pipeline config run when no run_dir is given
    fallback_config: str = "configs/synthetic.yaml"  # ... when the sequence of ``config`` is not on disk
    fallback_set: tuple[str, ...] = ("dataset.synthetic.scene=street", "dataset.synthetic.n_movers=0")
    run_dir: str = ""  # a finished `vslam run` folder (trajectory.tum.txt, groundtruth.tum.txt, stats.csv)
    dt_imu: float = 0.01  # s
    gnss_rate_hz: float = 10.0
    blocked: tuple[float, float] = (0.4, 0.8)  # fully blocked from / to this fraction of the drive
    vo_drift_per_m: float = 0.01  # VIO variance model (validity.vio_modes): 1 % of distance, as in `validity`
    quick_frames: int = 80  # --quick: vslam runs on the first frames only (KITTI 07: 8 s, ~45 m)
    imu_grades: tuple[str, ...] = ("tactical", "automotive")  # keys of IMU_GRADES; the first one writes report.md


@dataclass
class VslamTrack:
    """A vslam run reduced to what the experiment needs: ground truth and the tracked estimate (same clock)."""

    groundtruth: Trajectory
    estimate: Trajectory  # tracked frames only (predicted / uninitialised frames carry no measurement)
    monocular: bool
    source: str


def load_run(run_dir: str | Path) -> VslamTrack:
    """A `vslam run` output folder -> VslamTrack; frames with tracked=0 in stats.csv are left out.

    The estimate is trajectory.tum.txt, the poses as produced frame by frame: what a navigation system has
    at that moment (trajectory_final.tum.txt holds later corrections: back-filled frames, loop closures)."""
    d = Path(run_dir)
    for name in ("trajectory.tum.txt", "groundtruth.tum.txt"):
        if not (d / name).is_file():
            raise ConfigError(f"{d}: no {name}; give the output folder of a `vslam run` on a sequence with ground truth")
    est = read_trajectory(d / "trajectory.tum.txt", "tum")
    gt = read_trajectory(d / "groundtruth.tum.txt", "tum")
    # the drive is the part of the sequence the run covered (a run with max_frames writes the full ground truth)
    gt = gt.subset(np.flatnonzero((gt.timestamps >= est.timestamps[0] - 1e-6) & (gt.timestamps <= est.timestamps[-1] + 1e-6)))
    keep = np.ones(len(est), bool)
    if (d / "stats.csv").is_file():
        with open(d / "stats.csv", newline="") as f:
            tracked = {round(float(r["timestamp"]), 6): r["tracked"] == "1" for r in csv.DictReader(f)}
        keep = np.array([tracked.get(round(float(t), 6), True) for t in est.timestamps])
    mono = False
    if (d / "config.yaml").is_file():
        import yaml

        mono = ((yaml.safe_load((d / "config.yaml").read_text()) or {}).get("dataset") or {}).get("sensor") == "mono"
    return VslamTrack(gt, est.subset(np.flatnonzero(keep)), mono, str(d))


def run_vslam(cfg: VslamValidityConfig, out_dir: Path, root: Path, max_frames: int = 0) -> VslamTrack:
    """Run the pipeline on cfg.config (or the synthetic fallback when its data are missing) into out_dir."""
    from vslam.config import parse_overrides
    from vslam.errors import VslamError
    from vslam.pipeline import Pipeline, PipelineConfig, open_dataset

    path = Path(cfg.config) if Path(cfg.config).is_absolute() else root / cfg.config
    over: dict[str, Any] = {"output": {"dir": str(out_dir), "report": False}}
    if max_frames > 0:
        over["dataset"] = {"max_frames": max_frames}
    pcfg = PipelineConfig.load(path, over)
    try:
        seq = open_dataset(pcfg.dataset)
    except VslamError as e:  # real data absent: the synthetic street instead
        log.warning("%s; using %s with %s", e, cfg.fallback_config, " ".join(cfg.fallback_set))
        fb = Path(cfg.fallback_config) if Path(cfg.fallback_config).is_absolute() else root / cfg.fallback_config
        o = parse_overrides(list(cfg.fallback_set))
        o.setdefault("output", {}).update(over["output"])
        if max_frames > 0:
            o.setdefault("dataset", {})["max_frames"] = max_frames
        pcfg = PipelineConfig.load(fb, o)
        seq = open_dataset(pcfg.dataset)
    Pipeline(pcfg).run(seq)
    return dataclasses.replace(load_run(out_dir), source=seq.name)


def truth_of(gt: Trajectory, dt_imu: float) -> Truth:
    """Ground truth T_world_cam (vslam world = first camera) -> simulator truth in (North, Up, East), t from 0."""
    p = gt.poses[:, :3, 3] @ R_NAV_WORLD.T
    C = R_NAV_WORLD @ gt.poses[:, :3, :3] @ R_CAM_BODY
    return truth_from_samples(gt.timestamps, p, C, dt_imu)


def run_validity_vslam(out_dir: Path, seed: int = 0, quick: bool = False, run_dir: str | Path | None = None,
                       cfg: VslamValidityConfig = VslamValidityConfig()) -> dict[str, Any]:
    """Seed 000 mode choice with a real vslam trajectory as the VIO channel -> metrics (see module doc).

    run_dir: a finished `vslam run` folder (else cfg.run_dir, else vslam runs here on cfg.config, ~30 s).
    quick: vslam runs on the first cfg.quick_frames frames only (a smoke run; the drive is that short too)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    run_dir = run_dir or cfg.run_dir
    root = Path(__file__).resolve().parents[2]
    track = load_run(run_dir) if run_dir else run_vslam(cfg, out_dir / "vslam", root, cfg.quick_frames if quick else 0)
    if len(track.estimate) < 4:
        raise ConfigError(f"{track.source}: fewer than 4 tracked frames, nothing to feed the VIO channel")
    truth = truth_of(track.groundtruth, cfg.dt_imu)
    t0 = float(track.groundtruth.timestamps[0])
    dur = float(truth.t[-1])
    b0, b1 = cfg.blocked[0] * dur, cfg.blocked[1] * dur
    gnss = dataclasses.replace(GnssConfig(), rate_hz=cfg.gnss_rate_hz, outages=((b0, b1, 0),))
    unknown = [g for g in cfg.imu_grades if g not in IMU_GRADES]
    if not cfg.imu_grades or unknown:
        raise ConfigError(f"imu_grades must name some of {', '.join(IMU_GRADES)}; got {', '.join(cfg.imu_grades)}")
    vo_t = track.estimate.timestamps - t0
    path_m = float(np.sum(np.linalg.norm(np.diff(track.groundtruth.poses[:, :3, 3], axis=0), axis=1)))
    intro = [f"Drive: ground truth of `{track.source}` ({len(track.groundtruth)} poses, {path_m:.1f} m in {dur:.1f} s); "
             f"VIO channel: its vslam estimate, {len(track.estimate)} tracked frames "
             f"({'monocular, Sim3' if track.monocular else 'metric, SE3'}-aligned to GNSS/INS before the blockage). "
             f"GNSS {cfg.gnss_rate_hz:g} Hz, fully blocked {b0:.1f}-{b1:.1f} s. IMU: {cfg.imu_grades[0]} "
             f"(other grades in the sub-folders and below).", ""]
    by_imu: dict[str, dict[str, Any]] = {}
    for i, grade in enumerate(cfg.imu_grades):
        icfg = InsGnssConfig(trajectory=TrajectoryConfig(duration_s=dur, dt_imu=cfg.dt_imu), imu=IMU_GRADES[grade],
                             gnss=gnss, runs=1, filters=("mcc-srckf",))
        try:
            mi = run_validity(out_dir if i == 0 else out_dir / grade, seed=seed, vo_t=vo_t,
                              vo_p=track.estimate.poses[:, :3, 3], vo_drift_per_m=cfg.vo_drift_per_m, truth=truth,
                              cfg=icfg, vo_align="sim3" if track.monocular else "se3",
                              title=f"Priority mode choice with a real vslam trajectory as the VIO channel ({grade} IMU)",
                              extra=intro)
        except ValueError as e:  # a track that does not overlap the drive before the blockage
            raise ConfigError(f"{track.source}: {e}") from e
        by_imu[grade] = mi
    m = by_imu[cfg.imu_grades[0]]
    m["headline"] = f"{Path(track.source).name}, {path_m:.0f} m, GNSS blocked {b1 - b0:.1f} s, RMS while blocked: " + "; ".join(
        f"{grade} IMU: " + ", ".join(f"{k} {v:.2f} m" for k, v in mi["ours"]["rms_gnss_blocked"].items() if v is not None)
        for grade, mi in by_imu.items())
    m["ours"].update(source=track.source, path_m=path_m, tracked_frames=len(track.estimate),
                     by_imu={g: {"rms_gnss_blocked": mi["ours"]["rms_gnss_blocked"],
                                 "mode_share_blocked": mi["ours"]["mode_share_blocked"]} for g, mi in by_imu.items()})
    (out_dir / "metrics.json").write_text(json.dumps(m, indent=2))
    rows = [f"| {g} | " + " | ".join(f"{v:.2f}" if v is not None else "–" for v in mi["ours"]["rms_gnss_blocked"].values()) + " |"
            for g, mi in by_imu.items()]
    head = "| IMU | " + " | ".join(f"{k} m" for k in m["ours"]["rms_gnss_blocked"]) + " |"
    with open(out_dir / "report.md", "a") as f:
        f.write("\n## RMS while GNSS is blocked, per IMU grade\n\n" + head + "\n|" + "---|" * (len(rows[0].split("|")) - 2)
                + "\n" + "\n".join(rows) + "\n")
    return m
