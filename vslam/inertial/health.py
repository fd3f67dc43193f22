"""Whether the IMU is usable, frame by frame: stretches "off" where the accepted samples leave a hole.

A frame's interval (previous frame, this frame] is covered when the gated samples (``vslam.inertial.buffer``)
leave no hole over ``max_gap_s`` in it; a frame that is not covered starts a stretch "off", the next covered one
ends it. The tracker (``vslam.tracking.vio``) decides what off means for its state; this module only decides
and says so: one warning per stretch, and at the end of the run one for the rejected samples and one when the
IMU data ended before the images.
"""

from __future__ import annotations

import logging
from typing import Literal

from vslam.inertial.buffer import ImuBuffer

log = logging.getLogger(__name__)


class ImuHealth:
    """Coverage of the frames' intervals by ``buf``'s accepted samples (IMU-clock times)."""

    def __init__(self, buf: ImuBuffer, max_gap_s: float) -> None:
        self.buf, self.max_gap_s = buf, max_gap_s
        self.t_first: float | None = None
        self.t_prev: float | None = None
        self.off_since: float | None = None  # frame time that started the current stretch off
        self.why = ""

    @property
    def off(self) -> bool:
        return self.off_since is not None

    def frame(self, t: float) -> Literal["off", "on", ""]:
        """The frame at ``t`` (its samples already added): "off" / "on" when it starts / ends a stretch, else ""."""
        if self.t_first is None:
            self.t_first = t
        if self.t_prev is not None and t <= self.t_prev:  # a repeated timestamp keeps the state
            return ""
        ok, why = self.buf.covers(self.t_prev, t, self.max_gap_s)
        self.t_prev = t
        if not ok and self.off_since is None:
            log.warning("IMU off at t=%.3f s (%.2f s into the sequence): %s; tracking and local BA are visual-only "
                        "until good samples return", t, t - self.t_first, why)
            self.off_since, self.why = t, why
            return "off"
        if ok and self.off_since is not None:
            log.info("IMU usable again at t=%.3f s after %.2f s off", t, t - self.off_since)
            self.off_since, self.why = None, ""
            return "on"
        return ""

    def finish(self) -> None:
        """End of the run: one warning for the samples the gate rejected, one when the IMU ended before the images."""
        st = self.buf.finish()
        if st.n_rejected:
            log.warning("%s; they were left out", st.describe(self.t_first))
        t_end = self.buf.t_last
        if self.off_since is not None and self.why.startswith("no IMU samples after") and t_end is not None:
            log.warning("the IMU data ends at t=%.3f s (%.2f s into the sequence), %.2f s before the last image; "
                        "the frames after it ran visual-only", t_end, t_end - (self.t_first or t_end),
                        (self.t_prev or t_end) - t_end)
