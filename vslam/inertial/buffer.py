"""The IMU samples a visual-inertial run has received, gated (``vslam.inertial.gate``) as they arrive.

Samples come in per frame (those since the previous frame). The spike test of a sample looks at
``spike_window`` samples on each side, so a sample's decision is final once that many later samples have
arrived; the newest ones are decided on the neighbours there are so far (the frame's prediction cannot wait
for the next frame's samples) and decided again as their neighbours arrive. Rejections are counted when
final; ``finish`` settles the last ones.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from vslam.data.types import ImuSamples
from vslam.inertial.config import InertialConfig
from vslam.inertial.gate import OK, REASONS, gate_reasons

log = logging.getLogger(__name__)


@dataclass
class GateStats:
    """What the gate rejected among the final samples: counts by reason, and the first rejected sample
    (its time s, file and 1-based line when known, reason, and gyro (3,) rad/s + accel (3,) m/s^2 readings)."""

    seen: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    first_t: float | None = None
    first_source: str = ""
    first_line: int | None = None
    first_reason: str = ""
    first_values: np.ndarray | None = None

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def describe(self, t_start: float | None = None) -> str:
        """One line: how many, why, and the first one (file:line when known; its time after ``t_start`` too)."""
        why = ", ".join(f"{n} {r}" for r, n in self.rejected.items())
        where = f"t={self.first_t:.6f} s"
        if t_start is not None and self.first_t is not None:
            where += f", {self.first_t - t_start:.3f} s into the sequence"
        if self.first_line is not None:
            where = f"{self.first_source} line {self.first_line} ({where})"
        v = self.first_values
        vals = "" if v is None else f": gyro {np.array2string(v[:3], precision=4)} rad/s, accel {np.array2string(v[3:], precision=3)} m/s^2"
        return f"{self.n_rejected} of {self.seen} IMU samples rejected ({why}); the first at {where}{vals}"


class ImuBuffer:
    """Received IMU samples (IMU clock) with the gate's decisions; trimmed from the front as the IMU chain slides.

    ``t`` / ``gyro`` / ``accel`` are the accepted samples; ``upto`` and ``covers`` read only those.
    """

    def __init__(self, cfg: InertialConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else InertialConfig()
        self._t = np.zeros(0)
        self._gyro = np.zeros((0, 3))
        self._accel = np.zeros((0, 3))
        self._line = np.zeros(0, dtype=np.int64)  # -1: unknown
        self._reason = np.zeros(0, dtype=np.int8)
        self._final = 0  # samples [0, _final) are decided for good
        self.source = ""
        self.stats = GateStats()
        self._view()

    # -- accepted samples ------------------------------------------------------
    def _view(self) -> None:
        ok = self._reason == OK
        self.t, self.gyro, self.accel = self._t[ok], self._gyro[ok], self._accel[ok]

    @property
    def t_last(self) -> float | None:
        """Time of the newest sample received, accepted or not (None before any)."""
        return float(self._t[-1]) if len(self._t) else None

    def samples(self) -> ImuSamples:
        return ImuSamples(self.t, self.gyro, self.accel)

    def upto(self, t_end: float) -> ImuSamples:
        """The accepted samples, with the last one held to ``t_end`` when they stop short of it (the sample after a
        frame arrives with the next frame; holding it for < 1 IMU period is the only choice online; a longer hold
        is refused by preintegration's gap test)."""
        if len(self.t) and self.t[-1] < t_end:
            return ImuSamples(np.append(self.t, t_end), np.vstack([self.gyro, self.gyro[-1:]]),
                              np.vstack([self.accel, self.accel[-1:]]))
        return ImuSamples(self.t, self.gyro, self.accel)

    # -- input -----------------------------------------------------------------
    def add(self, s: ImuSamples | None) -> None:
        if s is None or len(s) == 0:
            return
        new = s.t > (self._t[-1] if len(self._t) else -np.inf)  # a repeated frame carries no new samples
        if not new.any():
            return
        n = int(new.sum())
        self._t = np.concatenate([self._t, s.t[new]])
        self._gyro = np.concatenate([self._gyro, s.gyro[new]])
        self._accel = np.concatenate([self._accel, s.accel[new]])
        line = s.line[new] if s.line is not None else np.full(n, -1, dtype=np.int64)
        self._line = np.concatenate([self._line, np.asarray(line, dtype=np.int64)])
        self._reason = np.concatenate([self._reason, np.zeros(n, dtype=np.int8)])
        if s.source:
            self.source = s.source
        self._decide(final_to=len(self._t) - self.cfg.spike_window)

    def finish(self) -> GateStats:
        """Settle the newest samples (no more will come) and return the statistics."""
        self._decide(final_to=len(self._t))
        return self.stats

    def _decide(self, final_to: int) -> None:
        """Gate the undecided samples on the neighbours there are; those below ``final_to`` become final."""
        k = self.cfg.spike_window
        lo = max(0, self._final - k)
        if len(self._t) > self._final:
            self._reason[self._final:] = gate_reasons(self._gyro[lo:], self._accel[lo:], self.cfg)[self._final - lo:]
        final_to = max(self._final, min(final_to, len(self._t)))
        for i in range(self._final, final_to):
            self._count(i)
        self._final = final_to
        self._view()

    def _count(self, i: int) -> None:
        st = self.stats
        st.seen += 1
        r = int(self._reason[i])
        if r == OK:
            return
        name = REASONS[r]
        st.rejected[name] = st.rejected.get(name, 0) + 1
        line = int(self._line[i]) if self._line[i] >= 0 else None
        log.debug("IMU sample at t=%.6f s (%s line %s) rejected: %s", self._t[i], self.source or "?", line, name)
        if st.first_t is None:
            st.first_t, st.first_source, st.first_line, st.first_reason = float(self._t[i]), self.source, line, name
            st.first_values = np.concatenate([self._gyro[i], self._accel[i]])

    def trim(self, t_keep: float) -> None:
        """Forget samples before ``t_keep`` (keeping one before it, and the context the undecided ones need)."""
        i = max(0, int(np.searchsorted(self._t, t_keep, side="left")) - 1)
        i = min(i, max(0, self._final - self.cfg.spike_window))
        if i == 0:
            return
        self._t, self._gyro, self._accel = self._t[i:], self._gyro[i:], self._accel[i:]
        self._line, self._reason = self._line[i:], self._reason[i:]
        self._final -= i
        self._view()

    # -- health -----------------------------------------------------------------
    def covers(self, t0: float | None, t1: float, max_gap_s: float) -> tuple[bool, str]:
        """Whether the accepted samples cover (t0, t1] with no hole over ``max_gap_s`` (the last sample before
        t1 held to it), and if not, why. t0 None (the first frame): a sample within ``max_gap_s`` before t1."""
        t = self.t
        if t0 is None:
            j = int(np.searchsorted(t, t1, side="right")) - 1
            if j >= 0 and t1 - t[j] <= max_gap_s:
                return True, ""
            return False, f"no accepted IMU sample within {max_gap_s} s before t={t1:.3f} s"
        i0 = int(np.searchsorted(t, t0, side="right"))  # first accepted sample after t0
        i1 = int(np.searchsorted(t, t1, side="right"))
        start = t[i0 - 1] if i0 > 0 else t0
        knots = np.concatenate([[start], t[i0:i1], [t1]])
        gaps = np.diff(knots)
        if len(gaps) and float(gaps.max()) <= max_gap_s:
            return True, ""
        j = int(np.argmax(gaps))
        raw = (self._t > knots[j]) & (self._t < knots[j + 1])
        if raw.any():
            why = REASONS[int(np.max(self._reason[raw]))]
            return False, f"{int(raw.sum())} IMU samples between t={knots[j]:.3f} and {knots[j + 1]:.3f} s rejected ({why})"
        if knots[j + 1] == t1 and (len(self._t) == 0 or self._t[-1] <= knots[j]):
            return False, f"no IMU samples after t={knots[j]:.3f} s"
        return False, f"a {gaps[j]:.3f} s gap between IMU samples at t={knots[j]:.3f} and {knots[j + 1]:.3f} s"
