"""The front end in a child process (``runtime.frontend_process``): same numbers as the thread, errors keep their
message, the child and its frame files go away, and a sequence that cannot be sent falls back to the thread."""

from __future__ import annotations

import csv
import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from tests._proc import environ_after_exec
from vslam.data.synthetic import SyntheticConfig, SyntheticSequence
from vslam.data.types import Frame
from vslam.errors import DatasetError
from vslam.pipeline import Pipeline, PipelineConfig
from vslam.runtime import RuntimeConfig
from vslam.features import FeatureConfig
from vslam.tracking.frontend_process import (FrontEndProcess, _ram_dir, frame_workers, one_at_a_time,
                                             ordered_frontends, read_frame_file, remove_stale_folders,
                                             write_frame_file)
from vslam.tracking.slam import SlamConfig

SMALL = dict(width=320, height=240, fx=262.5, fy=262.5, n_movers=0)


def _pc(tmp_path: Path, name: str, runtime: dict, n: int = 15) -> PipelineConfig:
    return PipelineConfig.load(None, {"dataset": {"kind": "synthetic", "sensor": "rgbd", "synthetic": {"n_frames": n, **SMALL}},
                                      "runtime": runtime, "output": {"dir": str(tmp_path / name), "report": False}})


def _stats(out: Path) -> list[dict[str, str]]:
    with open(out / "stats.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_frame_file_round_trip_maps_writable_arrays(tmp_path):
    path = tmp_path / "f.pkl"
    img = np.arange(7 * 9 * 3, dtype=np.uint8).reshape(7, 9, 3)
    obj = (Frame(3, 1.5, img, depth=np.linspace(0, 1, 63, dtype=np.float32).reshape(7, 9)),
           {"strided": np.arange(20.0).reshape(4, 5)[:, ::2], "empty": np.zeros((0, 2)), "text": "x"})
    write_frame_file(path, obj)
    frame, extra = read_frame_file(path)
    np.testing.assert_array_equal(frame.image, img)
    np.testing.assert_array_equal(frame.depth, obj[0].depth)
    np.testing.assert_array_equal(extra["strided"], obj[1]["strided"])
    assert extra["empty"].shape == (0, 2) and extra["text"] == "x" and frame.index == 3 and frame.timestamp == 1.5
    assert frame.image.flags.writeable
    frame.image[0, 0, 0] = 200  # a private copy of the page: the file keeps its bytes
    np.testing.assert_array_equal(read_frame_file(path)[0].image, img)


def _mapped_bytes(path: Path) -> int:
    """Bytes of this process's address space mapped from ``path`` (Linux)."""
    total = 0
    for line in Path("/proc/self/maps").read_text().splitlines():
        if line.endswith(str(path)) or line.endswith(f"{path} (deleted)"):
            lo, hi = line.split()[0].split("-")
            total += int(hi, 16) - int(lo, 16)
    return total


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/self/maps (Linux)")
def test_a_kept_array_keeps_only_its_own_pages_of_the_frame_file(tmp_path):
    """Issue 41: keyframes keep a frame's keypoints and descriptors, never its image or depth, so those pages must
    go with the frame (else a long run holds every keyframe's whole frame file)."""
    path = tmp_path / "f.pkl"
    img, depth = np.zeros((480, 640, 3), np.uint8), np.ones((480, 640), np.float32)
    desc = np.arange(1500 * 64, dtype=np.uint8).reshape(1500, 64) * 3  # 96 KB: a learned extractor's size
    kps = np.arange(3000.0).reshape(1500, 2)
    write_frame_file(path, (Frame(0, 0.0, img, depth=depth), {"desc": desc, "kps": kps}))
    frame, front = read_frame_file(path)
    path.unlink()  # as the tracking process does
    assert frame.image.nbytes + frame.depth.nbytes <= _mapped_bytes(path) < frame.image.nbytes + 2 * frame.depth.nbytes
    del frame
    np.testing.assert_array_equal(front["kps"], kps)  # small: a copy, no mapping
    np.testing.assert_array_equal(front["desc"], desc)
    assert 0 < _mapped_bytes(path) <= desc.nbytes + 4096
    del front
    assert _mapped_bytes(path) == 0


def test_process_thread_and_inline_front_ends_give_the_same_run(tmp_path):
    runs = {}
    modes = {"process": {}, "thread": {"frontend_process": False}, "inline": {"frontend_thread": False}}
    for name, slam in modes.items():
        runs[name] = Pipeline(_pc(tmp_path, name, slam)).run()
    for name in ("thread", "inline"):
        np.testing.assert_array_equal(runs[name].trajectory.poses, runs["process"].trajectory.poses)
        np.testing.assert_array_equal(runs[name].trajectory.timestamps, runs["process"].trajectory.timestamps)
    rows = _stats(tmp_path / "process")
    assert len(rows) == 15 and all(float(r["ms_features"]) > 0 for r in rows)  # timed in the child, reported here
    assert [r["n_features"] for r in rows] == [r["n_features"] for r in _stats(tmp_path / "thread")]


def test_child_stops_and_its_frame_files_go_away(tmp_path):
    seq = SyntheticSequence(SyntheticConfig(n_frames=12, **SMALL), sensor="rgbd")
    child = FrontEndProcess(seq, 12, seq.calibration, "rgbd", SlamConfig(), ahead=3)
    folder, proc = child._dir, child._proc
    it = iter(child)
    frames = [next(it) for _ in range(2)]
    assert [f.index for f, _ in frames] == [0, 1] and len(frames[0][1].feats) > 0
    assert not (folder / "spec.pkl").exists()  # read once, then removed
    child.close()  # early stop: the child is killed, not waited for
    assert proc.poll() is not None and not folder.exists()
    full = FrontEndProcess(seq, 5, seq.calibration, "rgbd", SlamConfig(), blas_threads=1, ahead=2)
    assert b"OPENBLAS_NUM_THREADS=1" in environ_after_exec(full._proc.pid, b"vslam.tracking.frontend_process")
    # ends by itself after n frames
    assert [f.index for f, _ in full] == [0, 1, 2, 3, 4]
    assert full._proc is None and not full._dir.exists()


class _FailingSequence(SyntheticSequence):
    """Decodes three frames, then meets a bad file (importable by the child: tests is a package)."""

    def __iter__(self):
        for k, frame in enumerate(super().__iter__()):
            if k == 3:
                raise DatasetError("rgb/0003.png", "not a PNG file", line=4)
            yield frame


def test_an_error_in_the_child_is_raised_with_its_type_and_message_after_the_frames_before_it(tmp_path):
    seq = _FailingSequence(SyntheticConfig(n_frames=8, **SMALL), sensor="rgbd")
    with pytest.raises(DatasetError, match=r"rgb/0003.png:4: not a PNG file") as err:
        Pipeline(_pc(tmp_path, "fail", {})).run(seq)
    assert err.value.line == 4
    lines = (tmp_path / "fail" / "trajectory.tum.txt").read_text().splitlines()
    assert len([x for x in lines if not x.startswith("#")]) == 3  # written as they were tracked


class _UnpicklableSequence(SyntheticSequence):
    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.lock = threading.Lock()  # e.g. a reader holding a handle


def test_a_sequence_that_cannot_be_sent_runs_on_the_thread(tmp_path, caplog):
    seq = _UnpicklableSequence(SyntheticConfig(n_frames=6, **SMALL), sensor="rgbd")
    ref = Pipeline(_pc(tmp_path, "ref", {"frontend_process": False}, n=6)).run()
    with caplog.at_level(logging.INFO, logger="vslam.pipeline"):
        res = Pipeline(_pc(tmp_path, "fallback", {}, n=6)).run(seq)
    assert "front end on a thread" in caplog.text
    np.testing.assert_array_equal(res.trajectory.poses, ref.trajectory.poses)


class _WarningSequence(SyntheticSequence):
    def __iter__(self):
        for k, frame in enumerate(super().__iter__()):
            if k == 2:
                logging.getLogger("vslam.data.synthetic").warning("frame %d: a test warning from the reader", k)
            yield frame


def test_the_child_s_log_records_reach_this_process_s_loggers(tmp_path, caplog):
    seq = _WarningSequence(SyntheticConfig(n_frames=4, **SMALL), sensor="rgbd")
    with caplog.at_level(logging.INFO):
        Pipeline(_pc(tmp_path, "warn", {}, n=4)).run(seq)
    hits = [r for r in caplog.records if "a test warning from the reader" in r.getMessage()]
    assert len(hits) == 1 and hits[0].name == "vslam.data.synthetic" and hits[0].levelname == "WARNING"
    assert hits[0].getMessage() == "frame 2: a test warning from the reader"


def test_frame_files_leave_a_nearly_full_ram_disk_alone():
    assert _ram_dir(min_free=1 << 62) is None  # the default temp folder then


def test_folders_of_runs_that_died_are_removed_and_live_ones_kept(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # its pid is free now (reuse within this test is practically impossible)
    (tmp_path / f"vslam-frontend-{dead.pid}-abc").mkdir()
    (tmp_path / f"vslam-frontend-{dead.pid}-abc" / "3.pkl").write_bytes(b"x")
    (tmp_path / f"vslam-frontend-{os.getpid()}-def").mkdir()
    (tmp_path / "vslam-frontend-notapid-x").mkdir()
    assert remove_stale_folders(tmp_path) == [tmp_path / f"vslam-frontend-{dead.pid}-abc"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"vslam-frontend-{os.getpid()}-def", "vslam-frontend-notapid-x"]


class _SlowTracker:
    """A front end that takes a random time (frames finish out of order) and records how many run at once."""

    def __init__(self, rng: np.random.Generator, state: dict) -> None:
        self._rng, self._state = rng, state

    def frontend(self, frame: Frame) -> int:
        with self._state["lock"]:
            self._state["running"] += 1
            self._state["started"] += 1
            self._state["most"] = max(self._state["most"], self._state["running"])
            pause = float(self._rng.uniform(0.0, 0.01))
        threading.Event().wait(pause)
        with self._state["lock"]:
            self._state["running"] -= 1
        if frame.index == self._state.get("fail_at"):
            raise ValueError(f"frame {frame.index} failed")
        return frame.index * 10


def _frames(n: int) -> list[Frame]:
    return [Frame(k, float(k), np.zeros((2, 2), np.uint8)) for k in range(n)]


def _trackers(n: int, state: dict) -> list[_SlowTracker]:
    state.update(lock=threading.Lock(), running=0, most=0, started=0)
    return [_SlowTracker(np.random.default_rng(k), state) for k in range(n)]


def test_frames_made_at_once_come_back_in_order_and_stay_within_ahead():
    state: dict = {}
    acks = threading.Semaphore(0)  # one per frame taken, as the parent's acknowledgement bytes
    read = []

    def seq():
        for f in _frames(40):
            read.append(f.index)
            yield f

    out, in_flight, held = [], [], []
    for item in ordered_frontends(seq(), 30, _trackers(3, state), 5, acks.acquire):
        in_flight.append(state["started"] - len(out))
        held.append(len(read) - len(out))
        out.append(item)
        acks.release()
    assert [f.index for f, _ in out] == list(range(30)) and [r for _, r in out] == [10 * k for k in range(30)]
    assert 1 < state["most"] <= 3 and max(in_flight) <= 5 and max(held) <= 3 + 1 and len(read) == 30


def test_a_front_end_error_is_raised_after_the_frames_before_it():
    state: dict = {"fail_at": 5}
    got = []
    with pytest.raises(ValueError, match="frame 5 failed"):
        for frame, _ in ordered_frontends(_frames(12), 12, _trackers(2, state), 8, lambda: True):
            got.append(frame.index)
    assert got == [0, 1, 2, 3, 4]


def test_a_reader_error_is_raised_in_its_place_and_a_stopped_parent_ends_the_frames():
    def seq():
        yield from _frames(3)
        raise DatasetError("cam0/3.png", "image does not decode")

    state: dict = {}
    got = []
    with pytest.raises(DatasetError, match="does not decode"):
        for frame, _ in ordered_frontends(seq(), 10, _trackers(2, state), 8, lambda: True):
            got.append(frame.index)
    assert got == [0, 1, 2]
    items = list(ordered_frontends(_frames(10), 10, _trackers(2, state), 2, lambda: False))
    assert [f.index for f, _ in items[:-1]] == [0, 1] and items[-1] is None


def test_workers_default_to_two_for_stereo_without_a_network_and_never_exceed_ahead(monkeypatch):
    from vslam import childproc

    monkeypatch.setattr(childproc, "usable_cpus", lambda: 2)
    assert frame_workers(SlamConfig(), RuntimeConfig(), "stereo", 8) == 2 and frame_workers(SlamConfig(), RuntimeConfig(), "stereo", 1) == 1
    assert frame_workers(SlamConfig(), RuntimeConfig(), "rgbd", 8) == 1
    assert frame_workers(SlamConfig(), RuntimeConfig(frontend_workers=3), "rgbd", 8) == 3
    assert frame_workers(SlamConfig(features=FeatureConfig(extractor="convpoint")), RuntimeConfig(), "stereo", 8) == 1
    monkeypatch.setattr(childproc, "usable_cpus", lambda: 1)
    assert frame_workers(SlamConfig(), RuntimeConfig(), "stereo", 8) == 1


def test_one_at_a_time_reads_after_the_parent_took_frame_k_minus_ahead():
    state: dict = {}
    taken = []
    out = list(one_at_a_time(_frames(10), 6, _trackers(1, state)[0], 2, lambda: taken.append(1) or True))
    assert [f.index for f, _ in out] == list(range(6)) and [r for _, r in out] == [10 * k for k in range(6)]
    assert len(taken) == 6 - 2
    assert list(one_at_a_time(_frames(10), 6, None, 0, lambda: False)) == [None]


def test_one_and_two_front_end_workers_give_the_same_run(tmp_path):
    one = Pipeline(_pc(tmp_path, "one", {"frontend_workers": 1}, n=12)).run()
    two = Pipeline(_pc(tmp_path, "two", {"frontend_workers": 2}, n=12)).run()
    traj = "trajectory.tum.txt"
    assert (tmp_path / "one" / traj).read_bytes() == (tmp_path / "two" / traj).read_bytes()
    np.testing.assert_array_equal(one.trajectory.poses, two.trajectory.poses)
