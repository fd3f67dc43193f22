"""Pairing checked, not assumed: the report a reader fills when it pairs a second stream with its frames
(RGB-depth by nearest time, left-right by equal time), and the rules that turn a bad pairing into a warning
or an error.

- No pair at all is an error (the run could only have no depth / no stereo), naming the list, the counts,
  both time spans and how far apart the nearest images are.
- More than ``DROP_WARN_FRACTION`` of the frames without a partner is a warning naming the first few and why.
- Pairs that all sit at nearly the same offset, far from zero, or lists whose first and last times are both
  off by the same amount (and pair much better once that is removed), are a warning naming the shift: such
  pairs are made, but of images taken at different moments.
- A partner image that no frame can use (8-bit depth, depth of another size than the images) is an error
  when the sequence opens, naming the file and what was expected, not a skipped frame each time.
- Depth in a wrong unit (a depth scale off by 1000, PNGs written in another unit than the scale says) is a
  warning when the sequence opens: the first depth image's median, in metres after the depth scale, outside what
  an RGB-D camera sees, or too few valid pixels to tell.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Sequence as Seq

import numpy as np

from vslam.data.types import Association
from vslam.errors import DatasetError

# Above this fraction of frames left without a partner the pairing is warned about. The real TUM teddy subset
# leaves 7 of its 200 rgb images (3.5 %) without depth (gaps of ~60 ms in the Kinect's depth stream), the
# EuRoC V1_01 subset none of its left images: more than 5 % is a list that was cut, thinned or shifted.
DROP_WARN_FRACTION = 0.05
N_NAMED = 3  # files a warning names before "and N more"

# Plausible median depth (metres) of the valid pixels of one RGB-D frame. The sensors read from 0.25-0.5 m (Kinect
# v1 / v2 0.5 m, Azure Kinect 0.25 m, RealSense D4xx ~0.2-0.3 m) to 5-10 m (Azure Kinect 5.5 m, Kinect and D4xx
# about 8-10 m, where few pixels are still valid), and a scene's median sits well inside its sensor's range: TUM
# teddy's frames have medians of 0.9-4.1 m (2.1 m in its first). A depth scale off by 1000 puts the median at
# millimetres or kilometres, PNGs in tenths of the declared unit at a tenth (teddy: 0.21 m), TUM's 5000 units per
# metre read as millimetres (a ROS bag's default) at 5 times (teddy: 10.7 m): all outside. Not caught: a factor
# that keeps the median in range (millimetres read at TUM's 5000 units per metre: teddy 0.43 m).
DEPTH_MEDIAN_RANGE_M = (0.25, 10.0)
# Fewer valid (non-zero, finite) pixels than this in the first depth image: too few to trust, or not depth of
# this scene at all. Kinect and RealSense frames hold 60-90 % (teddy's first: 74 %); sunlight on a structured-
# light camera or a lens cap leaves a few percent.
DEPTH_MIN_VALID_FRACTION = 0.10

logger = logging.getLogger(__name__)


def _names(items: Seq[tuple[str, str]]) -> str:
    shown = ", ".join(name for name, _ in items[:N_NAMED])
    return shown + (f" and {len(items) - N_NAMED} more" if len(items) > N_NAMED else "")


def _s(x: float) -> str:
    """Seconds for a message: 3 decimals, or 3 significant digits below a millisecond (EuRoC's nanoseconds)."""
    return f"{x:.3f} s" if x == 0 or abs(x) >= 1e-3 else f"{x:.3g} s"


def nearest_gaps(t_a: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """(len(t_a),) seconds from each time in t_a to the nearest in t_b (sorted); inf when t_b is empty."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    if len(t_b) == 0:
        return np.full(len(t_a), np.inf)
    k = np.searchsorted(t_b, t_a)
    lo = np.abs(t_a - t_b[np.clip(k - 1, 0, len(t_b) - 1)])
    hi = np.abs(t_b[np.clip(k, 0, len(t_b) - 1)] - t_a)
    return np.minimum(lo, hi)


def report(
    kind: str, t_a: np.ndarray, names_a: Seq[str], t_b: np.ndarray, ia: np.ndarray, ib: np.ndarray,
    max_diff: float, why: str, unpaired_kept: bool,
) -> Association:
    """The Association of a pairing (ia, ib) of the sorted times t_a (frames, named names_a) and t_b (partners);
    ``why`` is the reason given for an unpaired frame ("no depth image within 0.02 s"), to which the distance
    to the nearest partner image is added."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    paired = np.zeros(len(t_a), bool)
    paired[ia] = True
    gaps = nearest_gaps(t_a, t_b)
    dropped = []
    for i in np.flatnonzero(~paired):
        g = gaps[i]
        taken = ", paired with a closer frame" if max_diff > 0 and g < max_diff else ""
        dropped.append((names_a[i], f"{why} (nearest {_s(g)} away{taken})" if np.isfinite(g) else why))
    offsets = t_b[ib] - t_a[ia]
    return Association(kind=kind, inputs=len(t_a), paired=len(ia), dropped=dropped, partners=len(t_b),  # type: ignore[arg-type]
                       unpaired_kept=unpaired_kept, max_offset_s=float(max_diff),
                       median_offset_s=float(np.median(offsets)) if len(offsets) else None)


def no_pairs_text(t_a: np.ndarray, t_b: np.ndarray, what_a: str, what_b: str, within: str, other_list: str) -> str:
    """Why nothing paired, for the error: the counts, both spans, the nearest distance and a hint at a shift."""
    if len(t_b) == 0:
        return f"no {what_a} image has a {what_b} image: {other_list} lists none"
    gap = float(nearest_gaps(t_a, t_b).min())
    start = float(t_b[0] - t_a[0])
    shifted = f"; {other_list} starts {abs(start):.3f} s {'after' if start > 0 else 'before'} the {what_a} images" \
        if abs(start) > gap else ""
    return (f"no {what_a} image has a {what_b} image {within} ({len(t_a)} {what_a} images {t_a[0]:.3f}-{t_a[-1]:.3f} s, "
            f"{len(t_b)} {what_b} images {t_b[0]:.3f}-{t_b[-1]:.3f} s; the nearest are {_s(gap)} apart{shifted}: "
            f"are {other_list}'s times shifted?)")


def associate(t_a: np.ndarray, t_b: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of two timestamp lists, as TUM's associate.py does it.

    Every pair closer than max_diff seconds is a candidate; candidates are
    taken greedily by increasing difference, skipping those whose either side
    is already used. Returns index arrays (ia, ib) sorted by ia.
    Candidates are found by binary search, O((N + M) log M), not all N*M pairs.
    """
    t_a = np.asarray(t_a, dtype=np.float64)
    t_b = np.asarray(t_b, dtype=np.float64)
    lo = np.searchsorted(t_b, t_a - max_diff, side="left")
    hi = np.searchsorted(t_b, t_a + max_diff, side="right")
    ia = np.repeat(np.arange(len(t_a)), hi - lo)
    ib = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)]) if len(t_a) else np.zeros(0, np.int64)
    diff = np.abs(t_a[ia] - t_b[ib])
    keep = diff < max_diff  # associate.py uses a strict bound
    ia, ib, diff = ia[keep], ib[keep], diff[keep]
    used_a = np.zeros(len(t_a), bool)
    used_b = np.zeros(len(t_b), bool)
    out_a: list[int] = []
    out_b: list[int] = []
    for k in np.lexsort((ib, ia, diff)):
        a, b = int(ia[k]), int(ib[k])
        if not used_a[a] and not used_b[b]:
            used_a[a] = used_b[b] = True
            out_a.append(a)
            out_b.append(b)
    order = np.argsort(out_a)
    return np.asarray(out_a, np.int64)[order], np.asarray(out_b, np.int64)[order]


def _suspect_shift(t_a: np.ndarray, t_b: np.ndarray, paired: int, max_diff: float) -> tuple[float, int] | None:
    """(shift s, pairs after removing it) when the partner list's first and last times are both off by about
    the same s, far beyond max_diff, and removing s pairs clearly more frames; else None."""
    if len(t_a) < 2 or len(t_b) < 2 or max_diff <= 0:
        return None
    s0, s1 = float(t_b[0] - t_a[0]), float(t_b[-1] - t_a[-1])
    if s0 * s1 <= 0 or abs(s0 - s1) > 2 * max_diff or min(abs(s0), abs(s1)) <= 2 * max_diff:
        return None
    s = 0.5 * (s0 + s1)
    ia, ib = associate(t_a + s, t_b, max_diff)
    if len(ia):  # refine: the median offset of the shifted pairs
        s += float(np.median(t_b[ib] - t_a[ia] - s))
        ia, ib = associate(t_a + s, t_b, max_diff)
    gain = len(ia) - paired
    return (s, len(ia)) if gain >= max(2, math.ceil(DROP_WARN_FRACTION * len(t_a))) else None


def check(
    assoc: Association, t_a: np.ndarray, t_b: np.ndarray, ia: np.ndarray, ib: np.ndarray, where: str | Path,
    what_a: str, what_b: str, logger: logging.Logger,
) -> None:
    """Warn (on ``logger``, prefixed by ``where``, the list or folder paired) about a pairing (ia, ib, as given to
    ``report``) that left more than DROP_WARN_FRACTION of the frames without a partner, or whose partner times
    look shifted; sets ``assoc.shift_s``."""
    n, k = assoc.inputs, len(assoc.dropped)
    if k and assoc.drop_rate > DROP_WARN_FRACTION:
        within = f"within {assoc.max_offset_s:g} s" if assoc.max_offset_s > 0 else "with the same timestamp"
        fate = f"they are frames without {what_b}" if assoc.unpaired_kept else "they are dropped"
        unpaired = np.ones(len(t_a), bool)
        unpaired[ia] = False
        gaps = nearest_gaps(np.asarray(t_a, np.float64)[unpaired], np.asarray(t_b, np.float64))
        lo, hi = _s(float(gaps.min())), _s(float(gaps.max()))
        near = f" (the nearest {what_b} image {lo if lo == hi else f'{lo} to {hi}'} away)" if np.isfinite(gaps).all() else ""
        logger.warning("%s: %d of %d %s images (%.0f %%) have no %s image %s%s; %s: %s", where, k, n, what_a,
                       100.0 * assoc.drop_rate, what_b, within, near, fate, _names(assoc.dropped))
    shift = _suspect_shift(np.asarray(t_a, np.float64), np.asarray(t_b, np.float64), assoc.paired, assoc.max_offset_s)
    if shift is not None:
        s, m = shift
        assoc.shift_s = s
        logger.warning("%s: the %s times look shifted by %+.3f s against the %s times: both lists' first and last "
                       "times are that far apart, and with the shift removed %d of %d %s images would pair instead "
                       "of %d. The pairs made join images taken %.3f s apart; check the timestamps", where, what_b, s,
                       what_a, m, n, what_a, assoc.paired, abs(s))
        return
    med = assoc.median_offset_s
    offsets = np.asarray(t_b, np.float64)[ib] - np.asarray(t_a, np.float64)[ia]
    # a nearly constant offset far from zero (streams in lockstep, one clock off), not two free-running streams,
    # whose nearest-time offsets spread over +-half a frame period around zero
    if med is not None and assoc.max_offset_s > 0 and assoc.paired >= 5 and abs(med) > 0.5 * assoc.max_offset_s \
            and float(np.median(np.abs(offsets - med))) < 0.25 * assoc.max_offset_s:
        assoc.shift_s = med
        logger.warning("%s: the %s images are paired at a median offset of %+.3f s (tolerance %g s): is one "
                       "stream's clock offset? pairs this far apart join images taken at different moments", where,
                       what_b, med, assoc.max_offset_s)


def check_depth_image(path: Path, raw: np.ndarray | None, size: tuple[int, int], dtypes: Seq[type],
                      expected: str, images: str, depth_scale: float | None = None,
                      scale_from: str = "depth_scale") -> float | None:
    """DatasetError(path) when the decoded depth image ``raw`` cannot be depth for images of ``size``
    (width, height): a dtype not in ``dtypes`` (8-bit: a converted or visualised copy) or another size.
    ``expected`` describes the depth format ("16-bit PNG, 5000 units per metre"); None (not decoded) passes:
    that frame is skipped later, with its warning.

    Returns the median of its valid pixels in metres (integer depth divided by ``depth_scale``, raw units per
    metre; float depth is metres), None when none is valid or ``raw`` is None. A median outside
    ``DEPTH_MEDIAN_RANGE_M`` or fewer than ``DEPTH_MIN_VALID_FRACTION`` valid pixels is a warning naming the
    file, the median and the scale, and ``scale_from`` (where the scale came from) as what to check."""
    if raw is None:
        return None
    hint = "; run with --sensor mono to go without depth"
    if raw.dtype not in [np.dtype(d) for d in dtypes] or raw.ndim != 2:
        what = f"{raw.dtype}" + (f", {raw.shape[2]} channels" if raw.ndim == 3 else "")
        what = f"{raw.dtype.itemsize * 8}-bit ({what})" if raw.dtype.kind in "ui" else what
        raise DatasetError(path, f"depth image is {what}, expected {expected}: it cannot be used as depth (a "
                                 f"converted or visualised copy?){hint}")
    h, w = raw.shape[:2]
    if (w, h) != tuple(size):
        raise DatasetError(path, f"depth image is {w}x{h}, the {images} are {size[0]}x{size[1]}: depth must be "
                                 f"registered to the images, at their size{hint}")
    return depth_plausibility(path, raw, depth_scale, scale_from)


def _metres(x: float) -> str:
    return f"{x:.0f}" if x >= 100 else f"{x:.3g}"


def depth_plausibility(path: Path, raw: np.ndarray, depth_scale: float | None, scale_from: str) -> float | None:
    """The median valid depth (metres) of ``raw``; warns when it or the share of valid pixels is implausible
    for an RGB-D camera (see ``check_depth_image``)."""
    is_float = raw.dtype.kind == "f"
    scale = 1.0 if is_float or depth_scale is None else float(depth_scale)
    scale_text = "1 (metres)" if is_float else f"1/{scale:g}"
    v = raw.astype(np.float64)
    valid = v[np.isfinite(v) & (v > 0)] / scale
    frac = valid.size / max(v.size, 1)
    median = float(np.median(valid)) if valid.size else None
    lo, hi = DEPTH_MEDIAN_RANGE_M
    check = f"is the depth unit right ({'float depth must be metres' if is_float else scale_from})?"
    if median is None:
        logger.warning("%s: no valid depth pixel in the first depth image (all 0 or not finite): is it depth of "
                       "these images? frames without depth lose their depth features", path)
    elif frac < DEPTH_MIN_VALID_FRACTION:
        logger.warning("%s: only %.1f %% of the first depth image's pixels are valid (expected at least %.0f %% for "
                       "an RGB-D camera; median %s m after depth scale %s): is it depth of these images, and %s",
                       path, 100.0 * frac, 100.0 * DEPTH_MIN_VALID_FRACTION, _metres(median), scale_text, check)
    elif not lo <= median <= hi:
        logger.warning("%s: median depth %s m after depth scale %s (expected %g-%g m for an RGB-D camera): %s",
                       path, _metres(median), scale_text, lo, hi, check)
    return median

