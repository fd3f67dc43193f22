"""The stage interface: a stage plugged into ``SlamTracker.stages`` is called at the documented points of every
frame, in order, and what its hooks return is what tracking uses (a filter's keypoints, a keyframe request)."""

from __future__ import annotations

import numpy as np

from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.tracking.slam import SlamConfig, SlamTracker
from vslam.tracking.stages import Stage

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)
TRACKING_HOOKS = ["on_frame", "filter", "on_features", "annotate", "predict", "measure", "on_pose", "drop",
                  "wants_keyframe"]


class Recorder(Stage):
    """Records every hook; keeps only the keypoints right of ``x_min``; asks for a keyframe when ``every_frame``."""

    name = "recorder"

    def __init__(self, x_min: float = 0.0, every_frame: bool = False):
        self.calls: list[tuple[int, str]] = []
        self.x_min, self.every_frame, self.frame = x_min, every_frame, -1

    def _log(self, hook: str) -> None:
        self.calls.append((self.frame, hook))

    def on_frame(self, frame):
        self.frame = frame.index
        self._log("on_frame")

    def filter(self, frame, front, feats, lines):
        self._log("filter")
        kept = np.flatnonzero(feats.uv[:, 0] >= self.x_min)
        return feats.subset(kept), lines, kept

    def on_features(self, slam, frame, feats, lines):
        self._log("on_features")
        assert (feats.uv[:, 0] >= self.x_min).all()

    def annotate(self, est):
        self._log("annotate")

    def predict(self, frame, T_pred):
        self._log("predict")
        return T_pred

    def measure(self, slam, frame, feats, ur, T_pred, res):
        self._log("measure")
        return res

    def on_pose(self, slam, frame, ok):
        self._log("on_pose")

    def drop(self, slam, ok, res, feats, depth, ur):
        self._log("drop" if res is not None else "drop_first")
        return feats, depth, ur

    def wants_keyframe(self, frame, res, status):
        self._log("wants_keyframe")
        return self.every_frame and res.ok

    def on_keyframe(self, slam, kf, frame, res):
        self._log("on_keyframe" if res is not None else "on_first_keyframe")

    def after_mapping(self, slam, kf):
        self._log("after_mapping")

    def after_local_ba(self, slam, kf, image):
        self._log("after_local_ba")
        return {"recorder": 1.0}

    def end_frame(self, slam):
        self._log("end_frame")

    def report(self, est, front):
        self._log("report")
        est.times_ms["recorder"] = 1.0

    def finish(self, slam, out):
        self._log("finish")
        return {}


def _run(stage: Recorder, n: int = 12, tmp=None):
    seq = SyntheticSequence(SyntheticConfig(n_frames=n, **SMALL), sensor="rgbd")
    st = SlamTracker(seq.calibration, "rgbd", SlamConfig())
    st.stages.append(stage)
    ests = [st.track(f) for f in seq]
    if tmp is not None:
        st.finish(tmp)
    return st, ests


def test_hooks_run_in_the_documented_order(tmp_path):
    rec = Recorder()
    st, ests = _run(rec, tmp=tmp_path)
    first = [h for f, h in rec.calls if f == 0]
    assert first == ["on_frame", "filter", "on_features", "annotate", "on_first_keyframe", "after_local_ba", "drop_first",
                     "end_frame", "report"]
    for f in range(1, 12):
        hooks = [h for i, h in rec.calls if i == f and h != "finish"]
        assert hooks[:len(TRACKING_HOOKS)] == TRACKING_HOOKS, (f, hooks)
        assert hooks[-2:] == ["end_frame", "report"]
        if "on_keyframe" in hooks:  # a keyframe: before local mapping, after it, after its local BA
            assert hooks[len(TRACKING_HOOKS):-2] == ["on_keyframe", "after_mapping", "after_local_ba"]
            assert ests[f].times_ms["map_recorder"] == 1.0  # the step's ms, as the loop step's
    assert rec.calls[-1][1] == "finish"
    assert all(e.times_ms["recorder"] == 1.0 for e in ests)


def test_a_filter_decides_which_keypoints_are_tracked():
    rec = Recorder(x_min=160.0)
    st, ests = _run(rec)
    assert all(e.tracked for e in ests)
    raw = st.view.front.feats.uv
    assert st.view.kept is not None and (raw[st.view.kept, 0] >= 160).all()
    assert len(st.view.kept) < 0.8 * len(raw)
    assert all(e.n_features == len(st.view.kept) for e in ests[-1:])


def test_a_stage_keyframe_request_makes_a_keyframe():
    plain, _ = _run(Recorder())
    every, ests = _run(Recorder(every_frame=True))
    assert len(every.map.keyframes) == sum(e.tracked for e in ests) > len(plain.map.keyframes)


def test_loop_closing_is_the_first_stage():
    """With loop closing on, the loop closer is a stage, first in the list (a lost frame is relocalised by place
    recognition before lines or dense tracking measure it); off, there is none."""
    from vslam.loop.config import LoopConfig
    from vslam.tracking.dense import DenseConfig
    from vslam.tracking.stages.loop import LoopStage

    seq = SyntheticSequence(SyntheticConfig(n_frames=2, **SMALL), sensor="rgbd")
    on = SlamTracker(seq.calibration, "rgbd", SlamConfig(loop=LoopConfig(enabled=True), dense=DenseConfig(enabled=True)))
    assert isinstance(on.stages[0], LoopStage) and on.loop is on.stages[0].loop
    assert [s.name for s in on.stages] == ["loop", "dense"]
    off = SlamTracker(seq.calibration, "rgbd", SlamConfig())
    assert off.loop is None and all(s.name != "loop" for s in off.stages)
