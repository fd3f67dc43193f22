"""Experiments of seed 003 ch. 2 (INS/GNSS filter comparison) and seed 000 (validity, mode choice)."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from vslam.config import to_dict
from vslam.fusion.exp_common import md_table, pyplot, write_outputs
from vslam.fusion.ins_gnss import InsGnssConfig, improvement, monte_carlo, rms, run_filter, simulate_run
from vslam.fusion.simulate import GnssConfig, TrajectoryConfig, Truth, drifting_vo_track
from vslam.fusion.validity import (
    ModeEstimate, choose_modes, decision_rates, interp_track, quantile_factor, vio_modes,
)

log = logging.getLogger(__name__)

SEED_003 = "seed 003 ch. 2: adaptive robust SR-CKF 10-25 % lower error than EKF and 5-15 % lower than CKF"
SEED_000 = ("seed 000 §4: valid measurements lie within +-3 sigma with probability 0.997; "
            "priority mode r_opt = argmin J(r) (eq. 11)")


def ins_gnss_config(quick: bool) -> InsGnssConfig:
    """Default: 300 s drive, 10 runs (~20 s on one core); quick: 60 s, 2 runs."""
    filters = ("ekf", "ckf", "arsckf", "mcc-srckf")
    if not quick:
        return InsGnssConfig(filters=filters)
    g = dataclasses.replace(GnssConfig(), outages=((30.0, 40.0, 3), (45.0, 52.0, 0)))
    return InsGnssConfig(trajectory=TrajectoryConfig(duration_s=60.0), gnss=g, runs=2, filters=filters)


def run_ins_gnss(out_dir: Path, seed: int = 0, quick: bool = False) -> dict[str, Any]:
    """EKF vs CKF vs adaptive robust SR-CKF, tightly coupled, Monte-Carlo RMS table + plots."""
    plt = pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = ins_gnss_config(quick)
    res = monte_carlo(cfg, seed)
    rob = res["arsckf"]["pos_rms"]
    ours = {n: {k: v for k, v in r.items() if k != "per_run_pos"} for n, r in res.items()}
    gains = {"arsckf_vs_ekf_pos_pct": improvement(res["ekf"]["pos_rms"], rob),
             "arsckf_vs_ckf_pos_pct": improvement(res["ckf"]["pos_rms"], rob),
             "mcc_vs_ckf_pos_pct": improvement(res["ckf"]["pos_rms"], res["mcc-srckf"]["pos_rms"]),
             "arsckf_vs_ekf_vel_pct": improvement(res["ekf"]["vel_rms"], res["arsckf"]["vel_rms"]),
             "arsckf_vs_ckf_vel_pct": improvement(res["ckf"]["vel_rms"], res["arsckf"]["vel_rms"])}
    rows = [[n, r["pos_rms"], r["vel_rms"], r["pos_rms_degraded"]] for n, r in res.items()]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    names = list(res)
    ax[0].bar(names, [res[n]["pos_rms"] for n in names], color="C0")
    ax[0].set_ylabel("RMS 3-D position error, m")
    ax[0].set_title(f"{cfg.runs} Monte-Carlo runs, {cfg.gnss.noise} noise + multipath")
    truth, f, w, gnss = simulate_run(cfg, np.random.default_rng(seed))
    for n in names:
        r = run_filter(n, truth, f, w, gnss, cfg, np.random.default_rng(seed + 1))
        ax[1].plot(r.t, np.linalg.norm(r.pos_err, axis=1), label=n, lw=1)
    for t0, t1, keep in cfg.gnss.outages:
        ax[1].axvspan(t0, t1, color="grey", alpha=0.2)
    ax[1].set_yscale("log"), ax[1].set_xlabel("t, s"), ax[1].set_ylabel("|position error|, m"), ax[1].legend()
    fig.tight_layout()
    fig.savefig(out_dir / "ins_gnss_rms.png", dpi=110)
    plt.close(fig)
    text = [md_table(["filter", "pos RMS m", "vel RMS m/s", "pos RMS m (<4 sats)"], rows), "",
            md_table(["comparison", "ours %", "seed %"],
                     [["ARSCKF vs EKF (pos)", gains["arsckf_vs_ekf_pos_pct"], "10-25"],
                      ["ARSCKF vs CKF (pos)", gains["arsckf_vs_ckf_pos_pct"], "5-15"],
                      ["MCC-SRCKF (no fading) vs CKF (pos)", gains["mcc_vs_ckf_pos_pct"], "-"]]),
            "", "EKF and CKF are within a fraction of a percent of each other: with satellites 22 000 km "
            "away the pseudorange model is almost linear over the state uncertainty, so the cubature rule "
            "buys nothing here; the gain comes from the correntropy weighting. The fading factor "
            "(eqs. 10-13) is triggered by innovation noise in a correctly modelled system and costs accuracy "
            "(compare arsckf with mcc-srckf)."]
    headline = (f"pos RMS EKF {ours['ekf']['pos_rms']:.2f} m, CKF {ours['ckf']['pos_rms']:.2f} m, "
                f"adaptive robust SR-CKF {ours['arsckf']['pos_rms']:.2f} m "
                f"({gains['arsckf_vs_ekf_pos_pct']:.0f} % better than EKF, {gains['arsckf_vs_ckf_pos_pct']:.0f} % than CKF; "
                f"without fading {ours['mcc-srckf']['pos_rms']:.2f} m)") if {"ekf", "ckf", "arsckf", "mcc-srckf"} <= set(ours) else ""
    metrics = {"seed_claim": SEED_003, "headline": headline, "ours": {"rms": ours, **gains}, "runs": cfg.runs}
    return write_outputs(out_dir, "INS/GNSS tight coupling: EKF vs CKF vs adaptive robust SR-CKF", metrics,
                         text, ["ins_gnss_rms.png"], to_dict(cfg))


def validity_config(quick: bool) -> InsGnssConfig:
    """A drive with an urban canyon and a long bridge/tunnel (GNSS fully blocked)."""
    if quick:
        g = dataclasses.replace(GnssConfig(), outages=((20.0, 30.0, 3), (35.0, 55.0, 0)))
        return InsGnssConfig(trajectory=TrajectoryConfig(duration_s=60.0), gnss=g, runs=1)
    g = dataclasses.replace(GnssConfig(), outages=((60.0, 90.0, 3), (120.0, 200.0, 0)))
    return InsGnssConfig(trajectory=TrajectoryConfig(duration_s=240.0), gnss=g, runs=1)


def _decision_table(innov: np.ndarray, labels: np.ndarray) -> list[dict[str, float]]:
    out = []
    for conf in (0.6827, 0.9, 0.9545, 0.99, 0.9973, 0.9999):
        k = quantile_factor(conf)
        d = decision_rates(innov, labels, k)
        out.append({"confidence": conf, "k": k, "false_alarm": d.false_alarm, "missed": d.missed, "cost": d.cost})
    return out


def align_to_nav(vo_t: np.ndarray, vo_p: np.ndarray, nav_t: np.ndarray, nav_pos: np.ndarray, use: np.ndarray,
                 with_scale: bool) -> tuple[np.ndarray, int]:
    """A VO track in its own frame -> navigation axes, by Umeyama (Sim3 when ``with_scale``: monocular) to the
    GNSS/INS solution at the epochs ``use`` inside the track's span. The caller passes the epochs with a fix
    (>= 4 satellites) before GNSS is blocked: what a vehicle knows at hand-over, no ground truth.
    -> (positions (T, 3), epochs used)."""
    from evo.core.geometry import umeyama_alignment

    sel = np.flatnonzero(use & (nav_t >= vo_t[0]) & (nav_t <= vo_t[-1]))
    if len(sel) < 3:
        raise ValueError("fewer than 3 valid GNSS/INS epochs overlap the VO track before the blockage: it cannot be aligned")
    src = interp_track(vo_t, vo_p, nav_t[sel])
    R, t, c = umeyama_alignment(src.T, nav_pos[sel].T, with_scale)
    return c * vo_p @ R.T + t, len(sel)


def run_validity(out_dir: Path, seed: int = 0, quick: bool = False, vo_t: np.ndarray | None = None,
                 vo_p: np.ndarray | None = None, vo_drift_per_m: float = 0.01, truth: Truth | None = None,
                 cfg: InsGnssConfig | None = None, vo_align: str = "none", title: str = "",
                 extra: list[str] | None = None) -> dict[str, Any]:
    """Limit-value validity + priority mode choice; (vo_t, vo_p) = a VO/VIO track (e.g. a vslam run),
    synthetic drifting track by default. truth: an external drive for the simulator (``truth_from_samples``)
    instead of cfg's; vo_align "se3"/"sim3": the track is in its own frame, aligned by ``align_to_nav``."""
    plt = pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = cfg if cfg is not None else validity_config(quick)
    rng = np.random.default_rng(seed)
    truth, f, w, gnss = simulate_run(cfg, rng, truth)
    nav = run_filter("mcc-srckf", truth, f, w, gnss, cfg, np.random.default_rng(seed + 1))
    table = _decision_table(nav.pr_innov, gnss.is_outlier)
    if vo_t is None or vo_p is None:
        vo_t, vo_p = truth.t, drifting_vo_track(truth.t, truth.p, rng, vo_drift_per_m)
    m = 2 * nav.visible
    nis_ok = np.where(m > 0, nav.nis * np.maximum(m, 1) <= stats.chi2.ppf(0.9973, np.maximum(m, 1)), True)
    gnss_mode = ModeEstimate("GNSS+INS", nav.pos, nav.pos_cov, nis_ok)
    anchor_ok = (nav.visible >= 4) & nis_ok
    n_align = 0
    if vo_align != "none":
        dark = np.flatnonzero(nav.visible == 0)
        before = nav.t < (nav.t[dark[0]] if len(dark) else np.inf)
        vo_p, n_align = align_to_nav(vo_t, vo_p, nav.t, nav.pos, (nav.visible >= 4) & before, vo_align == "sim3")
    vio, vio_gnss = vio_modes(nav.t, vo_t, vo_p, nav.pos, nav.pos_cov, anchor_ok, vo_drift_per_m, 0.05)
    modes = [gnss_mode, vio, vio_gnss]
    idx, fused = choose_modes(modes, hold=3)
    p_true = interp_track(truth.t, truth.p, nav.t)
    blocked = nav.visible == 0
    errs = {mm.name: mm.pos - p_true for mm in modes} | {"r_opt": fused - p_true}
    # a visual mode counts only where its track exists (a vslam run may start after the drive)
    span = {"VIO": vio.valid, "VIO+GNSS": vio_gnss.valid}
    rms_all = {k: rms(e[span[k]]) if k in span else rms(e) for k, e in errs.items()}
    rms_blk = {k: rms(e[blocked & span.get(k, True)]) if (blocked & span.get(k, True)).any() else float("nan")
               for k, e in errs.items()}
    share = {mm.name: float(np.mean(idx[blocked] == i)) if blocked.any() else 0.0 for i, mm in enumerate(modes)}
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for k, e in errs.items():
        ax[0].plot(nav.t, np.linalg.norm(e, axis=1), label=k, lw=2 if k == "r_opt" else 1)
    ax[0].set_yscale("log"), ax[0].set_ylabel("|position error|, m"), ax[0].legend()
    ax[1].step(nav.t, idx, where="post")
    ax[1].set_yticks(range(len(modes)), [mm.name for mm in modes]), ax[1].set_xlabel("t, s")
    for t0, t1, _ in cfg.gnss.outages:
        for a in ax:
            a.axvspan(t0, t1, color="grey", alpha=0.2)
    fig.tight_layout(), fig.savefig(out_dir / "mode_choice.png", dpi=110), plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([r["k"] for r in table], [r["false_alarm"] for r in table], "o-", label="false alarm")
    ax.plot([r["k"] for r in table], [r["missed"] for r in table], "s-", label="missed gross error")
    ax.set_xlabel("limit k (interval +-k sigma)"), ax.set_ylabel("rate"), ax.legend()
    fig.tight_layout(), fig.savefig(out_dir / "decision_rates.png", dpi=110), plt.close(fig)
    three = next(r for r in table if abs(r["k"] - 3.0) < 0.01)
    text = [md_table(["confidence", "k", "false alarm", "missed", "cost (1:1)"],
                     [[r["confidence"], r["k"], r["false_alarm"], r["missed"], r["cost"]] for r in table]), "",
            "False alarms exceed the nominal 1 - confidence because the noise is a heavy-tailed mixture.", "",
            md_table(["mode", "RMS all m", "RMS GNSS blocked m", "share of blocked epochs"],
                     [[k, rms_all[k], rms_blk[k], share.get(k, "-")] for k in errs])]
    headline = (f"3-sigma limit: false alarm {three['false_alarm']:.3f}, missed {three['missed']:.3f}; "
                f"GNSS blocked: " + ", ".join(f"{k} {v:.1f} m" for k, v in rms_blk.items()))
    metrics = {"seed_claim": SEED_000, "headline": headline, "ours": {"three_sigma": three, "decision_table": table,
               "rms_all": rms_all, "rms_gnss_blocked": rms_blk, "mode_share_blocked": share,
               "blocked_epochs": int(blocked.sum()), "vo_align_epochs": n_align}}
    return write_outputs(out_dir, title or "Validity by limit values and priority mode choice", metrics,
                         (extra or []) + text, ["decision_rates.png", "mode_choice.png"], to_dict(cfg))
