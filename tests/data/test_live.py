"""Live input (vslam.data.live), tested on a lossless video opened as a device: every frame in order when the
queue is large, drops (counted, oldest first) when the video is paced at its rate and the consumer is slow,
a pipeline run with the stats.csv ``dropped`` column, and bad sources as one-line errors.

Drop counts depend on timing: they are asserted as inequalities and as sums that hold whatever the timing.
The Intel RealSense path needs a camera and ``pyrealsense2``: not tested here.
"""

from __future__ import annotations

import csv
import os
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.data.make_inputs import TEDDY_CAMERA, write_video
from vslam.cli import main
from vslam.data.live import FrameQueue, LiveConfig, LiveSequence
from vslam.data.registry import open_sequence
from vslam.errors import ConfigError, DatasetError
from vslam.paths import data_root
from vslam.pipeline import Pipeline, PipelineConfig

H, W = 48, 64
N = 40
CAMERA = "fx: 50.0\nfy: 51.0\ncx: 32.0\ncy: 24.0\n"


def _frames(n: int = N) -> list[np.ndarray]:
    """Random frames: each is told apart from the others by its pixels."""
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


@pytest.fixture
def clip(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    imgs = _frames()
    video = write_video(tmp_path / "clip.avi", imgs, fps=200.0)  # 5 ms per frame
    (tmp_path / "clip.yaml").write_text(CAMERA)
    return video, imgs


def test_frame_queue_keeps_the_newest() -> None:
    q, stop = FrameQueue(2), threading.Event()
    for i in range(5):
        q.put(i)
    q.close()
    assert [q.get(stop), q.get(stop), q.get(stop)] == [3, 4, None] and q.dropped == 3


def test_unpaced_with_a_large_queue_every_frame_in_order(clip: tuple[Path, list[np.ndarray]]) -> None:
    video, imgs = clip
    seq = open_sequence(str(video), kind="live", config=LiveConfig(queue=N, realtime=False))
    assert isinstance(seq, LiveSequence) and seq.sensor == "mono" and seq.calibration.cam0.fx == 50.0
    assert (seq.calibration.cam0.width, seq.calibration.cam0.height) == (W, H)
    with pytest.raises(TypeError, match="no length"):
        len(seq)
    frames = list(seq)
    assert [f.index for f in frames] == list(range(N)) and seq.dropped == 0
    for f, img in zip(frames, imgs):
        assert f.image.dtype == np.uint8 and np.array_equal(f.image, img)  # FFV1 is lossless
    # the container's times: 200 frames/s
    np.testing.assert_allclose(seq.timestamps(), np.arange(N) / 200.0, atol=1e-6)


def test_paced_with_a_slow_consumer_drops_the_oldest(clip: tuple[Path, list[np.ndarray]]) -> None:
    video, imgs = clip
    seq = LiveSequence(video, config=LiveConfig(queue=2, realtime=True))
    t0 = time.monotonic()
    got = []
    for f in seq:
        got.append(f)
        time.sleep(0.020)  # a tracker at 50 frames/s behind a 200 frames/s camera
    wall = time.monotonic() - t0
    idx = [f.index for f in got]
    assert wall >= 0.9 * (N - 1) / 200.0  # paced: not faster than the video's rate
    assert 2 <= len(got) < N and seq.dropped > 0
    assert len(got) + seq.dropped == N  # every frame either delivered or counted as dropped
    assert idx == sorted(set(idx)) and idx[-1] == N - 1  # in order; the newest always survives
    assert np.all(np.diff(seq.timestamps()) > 0)
    for f in got:
        assert np.array_equal(f.image, imgs[f.index])  # the index says which frame it is


def test_stop_on_interrupt_ends_the_stream(clip: tuple[Path, list[np.ndarray]]) -> None:
    video, _ = clip
    seq = LiveSequence(video, config=LiveConfig(queue=2, realtime=True))
    got = []
    with seq.stop_on_interrupt():
        for f in seq:
            got.append(f.index)
            if len(got) == 3:
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C: the stream ends, no KeyboardInterrupt
                time.sleep(0.01)
    assert 3 <= len(got) < N
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def _stats(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.realdata
def test_pipeline_on_a_live_video_with_the_dropped_column(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    src = data_root() / "tum" / "rgbd_dataset_freiburg3_teddy"
    if not src.is_dir():
        pytest.skip(f"real data not found at {src} (set VSLAM_DATA to the folder holding tum/)")
    rows = [ln.split() for ln in (src / "rgb.txt").read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    n = 16  # frames: the monocular map initialises within them
    video = write_video(tmp_path / "teddy.avi", [cv2.imread(str(src / f)) for _, f in rows[:n]], fps=30.0)
    cam = tmp_path / "teddy.yaml"
    cam.write_text(TEDDY_CAMERA)
    common = ["--camera", str(cam), "--no-eval", "--set", "output.report=false"]

    # every frame (large queue, no pacing): deterministic, the video reader's trajectory
    out = tmp_path / "live"
    code = main(["run", "--live", str(video), *common, "--out", str(out), "--set", "dataset.live.queue=64",
                 "--set", "dataset.live.realtime=false"])
    printed = capsys.readouterr().out
    assert code == 0 and f"frames: {n} read, " in printed and "frames/s, 0 dropped by the live queue" in printed
    stats = _stats(out / "stats.csv")
    assert [int(r["index"]) for r in stats] == list(range(n)) and {r["dropped"] for r in stats} == {"0"}
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "video", "path": str(video), "camera": str(cam),
                                                 "sensor": "mono"},
                                     "output": {"dir": str(tmp_path / "video"), "report": False},
                                     "eval": {"enabled": False}})
    ref = Pipeline(cfg).run()
    assert ref.dropped is None and {r["dropped"] for r in _stats(tmp_path / "video" / "stats.csv")} == {"0"}
    live, video_traj = (np.loadtxt(d / "trajectory_final.tum.txt") for d in (out, tmp_path / "video"))
    assert len(live) == len(video_traj) == len(ref.trajectory) >= n // 2
    assert np.abs(live - video_traj).max() <= 1e-6  # times (s) and poses (metres, quaternions)

    # paced at 200 frames/s with the default queue of 2: the tracker is slower, frames are dropped
    fast = write_video(tmp_path / "fast.avi", [cv2.imread(str(src / f)) for _, f in rows[:n]], fps=200.0)
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "live", "path": str(fast), "camera": str(cam),
                                                 "sensor": "mono", "live": {"realtime": True}},
                                     "output": {"dir": str(tmp_path / "paced"), "report": False},
                                     "eval": {"enabled": False}})
    res = Pipeline(cfg).run()
    stats = _stats(tmp_path / "paced" / "stats.csv")
    idx = [int(r["index"]) for r in stats]
    dropped = [int(r["dropped"]) for r in stats]
    assert res.dropped == sum(dropped) > 0 and len(stats) < n
    assert idx == sorted(set(idx)) and idx[-1] + 1 == len(stats) + sum(dropped)  # gaps are the dropped frames
    assert np.all(np.diff([float(r["timestamp"]) for r in stats]) > 0)


@pytest.mark.parametrize("source, match", [
    ("97", "97: no camera at device index 97"),
    ("rtsp://127.0.0.1:9/none", "rtsp://127.0.0.1:9/none: the stream cannot be opened"),
    ("no_such_clip.avi", "no_such_clip.avi: not a live source: expected a camera device index"),
])
def test_bad_source_is_one_line(source: str, match: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(DatasetError, match=match):
        LiveSequence(source, camera=tmp_path / "camera.yaml")
    cam = tmp_path / "camera.yaml"
    cam.write_text(CAMERA)
    code = main(["run", "--live", source, "--camera", str(cam), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1] == f"vslam: error: {match}" + err[-1].split(match, 1)[1]


def test_live_config_errors(clip: tuple[Path, list[np.ndarray]], tmp_path: Path) -> None:
    video, _ = clip
    with pytest.raises(DatasetError, match="sensor 'rgbd' not available from this live source"):
        LiveSequence(video, sensor="rgbd")
    with pytest.raises(ConfigError, match="dataset.live.queue must be at least 1"):
        PipelineConfig.load(None, {"dataset": {"kind": "live", "path": str(video), "live": {"queue": 0}}})
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "live", "path": str(video), "sensor": "mono", "stride": 2},
                                     "output": {"dir": str(tmp_path / "o")}})
    with pytest.raises(ConfigError, match="a live source has none to select"):
        Pipeline(cfg).run()


def test_close_releases_the_source_iterated_or_not(clip: tuple[Path, list[np.ndarray]]) -> None:
    video, imgs = clip
    seq = LiveSequence(video, config=LiveConfig(queue=2, realtime=False))
    src = seq._src
    assert src is not None and src.cap.isOpened()
    seq.close()  # never iterated: the capture __init__ opened is released, and no grabber thread was started
    assert seq._src is None and not src.cap.isOpened() and seq._grabber is None
    seq.close()  # twice is fine

    with LiveSequence(video, config=LiveConfig(queue=2, realtime=True)) as seq:  # closed mid-iteration
        it = iter(seq)
        first = next(it)
        grabber = seq._grabber
        assert grabber is not None and grabber.is_alive() and np.array_equal(first.image, imgs[0])
    grabber.join(1.0)
    assert not grabber.is_alive() and not [t for t in threading.enumerate() if t is grabber]
    it.close()


def test_pipeline_closes_the_sequence_it_opened_only(clip: tuple[Path, list[np.ndarray]], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    video, _ = clip
    seen: list[LiveSequence] = []

    def fake_run(self, seq, out, progress):  # the run itself is not what is tested: it fails at once
        seen.append(seq)
        raise RuntimeError("stop here")

    monkeypatch.setattr(Pipeline, "_run", fake_run)
    cfg = PipelineConfig.load(None, {"dataset": {"kind": "live", "path": str(video), "sensor": "mono"},
                                     "output": {"dir": str(tmp_path / "o")}})
    with pytest.raises(RuntimeError, match="stop here"):
        Pipeline(cfg).run()
    assert isinstance(seen[0], LiveSequence) and seen[0]._src is None  # opened from the config: closed
    mine = LiveSequence(video, config=LiveConfig(realtime=False))
    with pytest.raises(RuntimeError, match="stop here"):
        Pipeline(cfg).run(mine)
    assert seen[1] is mine and mine._src is not None and mine._src.cap.isOpened()  # the caller's: left open
    mine.close()
