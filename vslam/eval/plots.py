"""Report figures as PNG bytes.

Figures are built on ``matplotlib.figure.Figure`` with an explicit Agg canvas,
never through pyplot: no GUI backend, no global figure state, no DISPLAY, and
nothing from evo's plot module, which would read/write ~/.evo/settings.json.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from vslam.eval.result import EvalArrays, EvalResult

FIGSIZE = (8.0, 5.0)  # inches
DPI = 100
AXES = "xyz"


def top_view_axes(xyz: np.ndarray) -> tuple[int, int]:
    """The two axes with the largest extent, in x<y<z order.

    A top view must show the ground plane: xy for TUM/EuRoC (z up), xz for
    KITTI camera frames (y down). The spread of the GT positions tells which.
    """
    extent = np.ptp(xyz, axis=0) if len(xyz) else np.zeros(3)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2])
    return int(a), int(b)


def trajectory_png(arrays: EvalArrays, alignment: str) -> bytes:
    """GT (dashed) and aligned estimate coloured by ATE, in the plane of largest extent."""
    fig, ax = _figure()
    i, j = top_view_axes(arrays.gt_xyz)
    ax.plot(arrays.gt_xyz[:, i], arrays.gt_xyz[:, j], "--", color="0.45", lw=1.2, label="ground truth")
    pts = arrays.est_xyz[:, [i, j]]
    if len(pts) > 1:
        segs = np.stack([pts[:-1], pts[1:]], axis=1)
        lc = LineCollection(segs, cmap="viridis", linewidths=1.6, label=f"estimate ({alignment} aligned)")
        lc.set_array(0.5 * (arrays.ate_t[:-1] + arrays.ate_t[1:]))
        ax.add_collection(lc)
        fig.colorbar(lc, ax=ax, label="ATE (m)")
    ax.plot(pts[:1, 0], pts[:1, 1], "o", color="tab:green", ms=5, label="start")
    ax.set_xlabel(f"{AXES[i]} (m)")
    ax.set_ylabel(f"{AXES[j]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectories (top view)")
    return _png(fig)


def ate_time_png(result: EvalResult) -> bytes:
    arrays = _arrays(result)
    fig, ax = _figure()
    x = arrays.t - arrays.t[0]
    ax.plot(x, arrays.ate_t, color="tab:blue", lw=1.0, label="ATE")
    s = result.ate.translation
    for value, name, style in ((s.rmse, "rmse", "-"), (s.mean, "mean", "--"), (s.median, "median", ":")):
        ax.axhline(value, color="tab:red", ls=style, lw=1.0, label=f"{name} {value:.4f} m")
    ax.set_xlabel(_time_label(result))
    ax.set_ylabel("ATE translation (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(f"Absolute trajectory error ({result.alignment.method} aligned)")
    return _png(fig)


def ate_hist_png(result: EvalResult) -> bytes:
    arrays = _arrays(result)
    fig, ax = _figure()
    bins = int(np.clip(np.sqrt(len(arrays.ate_t)), 10, 60))
    ax.hist(arrays.ate_t, bins=bins, color="tab:blue", alpha=0.8)
    ax.axvline(result.ate.translation.rmse, color="tab:red", lw=1.2, label=f"rmse {result.ate.translation.rmse:.4f} m")
    ax.set_xlabel("ATE translation (m)")
    ax.set_ylabel("poses")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("ATE distribution")
    return _png(fig)


def rpe_time_png(result: EvalResult) -> bytes | None:
    """RPE translation of the first configured delta over time; None without RPE."""
    arrays = _arrays(result)
    if not result.rpe or result.rpe[0].label not in arrays.rpe:
        return None
    stats = result.rpe[0]
    series = arrays.rpe[stats.label]
    fig, ax = _figure()
    x = arrays.t[series.index] - arrays.t[0]
    ax.plot(x, series.translation, color="tab:purple", lw=1.0, label=f"RPE per {stats.label}")
    ax.axhline(stats.translation.rmse, color="tab:red", lw=1.0, label=f"rmse {stats.translation.rmse:.4f} m")
    ax.set_xlabel(_time_label(result))
    ax.set_ylabel("RPE translation (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("Relative pose error")
    return _png(fig)


def _figure() -> tuple[Figure, Axes]:
    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _arrays(result: EvalResult) -> EvalArrays:
    if result.arrays is None:
        raise ValueError("this result has no per-pose arrays (read back from JSON?); re-run evaluate to plot")
    return result.arrays


def _time_label(result: EvalResult) -> str:
    return "time from start (s)" if result.time_unit == "s" else "frames from start"
