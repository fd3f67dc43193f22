"""Progress bars: on a terminal only (stderr), off with --quiet / VSLAM_PROGRESS=0 and in logs; the last line stays
with the totals; `vslam run` in a pseudo-terminal shows one."""

from __future__ import annotations

import io
import os
import pty
import re
import subprocess
import sys
from pathlib import Path

import pytest

from vslam.progress import bar_enabled, progress_bar


class Terminal(io.StringIO):
    """A stream that says it is a terminal (and has no size, as tqdm then sees it)."""

    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv("VSLAM_PROGRESS", raising=False)
    monkeypatch.delenv("RANK", raising=False)


def _lines(text: str) -> list[str]:
    """What stays on screen: each \\r rewrites the line."""
    return [ln.rsplit("\r", 1)[-1] for ln in text.split("\n")]


def test_on_for_a_terminal_off_for_a_log_quiet_or_env(monkeypatch):
    assert bar_enabled(stream=Terminal())
    assert not bar_enabled(stream=io.StringIO())  # a log file, a pipe, CI
    assert not bar_enabled(quiet=True, stream=Terminal())
    monkeypatch.setenv("RANK", "1")  # torchrun: rank 0 alone draws the training's bar
    assert not bar_enabled(stream=Terminal())
    monkeypatch.setenv("RANK", "0")
    assert bar_enabled(stream=Terminal())
    monkeypatch.setenv("VSLAM_PROGRESS", "0")
    assert not bar_enabled(stream=Terminal())
    log = io.StringIO()
    with progress_bar("tracking", 5, stream=log) as bar:
        for k in range(5):
            bar(k + 1, 5)
    assert log.getvalue() == ""


def test_last_line_keeps_count_rate_and_time():
    tty = Terminal()
    with progress_bar("tracking", stream=tty) as bar:  # the total comes with the first update (the pipeline's)
        for k in range(15):
            bar(k + 1, 15)
    text = tty.getvalue()
    assert text.endswith("\n")
    last = _lines(text)[-2]
    assert last.startswith("tracking: 100%") and "15/15" in last and "frame/s" in last, repr(last)


def _read_all(fd: int) -> str:
    """Everything written to a pty so far: one read returns only what the line discipline has passed on yet
    (the first redraw, at times), so read until nothing more comes."""
    import select

    chunks = []
    while select.select([fd], [], [], 0.5)[0]:
        chunks.append(os.read(fd, 65536))
    return b"".join(chunks).decode()


def test_shows_on_a_terminal_that_reports_no_size():
    """A pseudo-terminal nobody sized (0 x 0: `script` from a pipe, `docker exec -t`) made tqdm hide the bar."""
    master, slave = pty.openpty()
    with os.fdopen(slave, "w") as tty:
        assert os.get_terminal_size(tty.fileno()) == (0, 0)
        with progress_bar("detecting", 3, unit="image", stream=tty) as bar:
            for k in range(3):
                bar(k + 1, 3)
        tty.flush()
        out = _read_all(master)
    os.close(master)
    assert "3/3" in out and "image/s" in out


def test_an_error_before_any_work_leaves_no_bar():
    tty = Terminal()
    with pytest.raises(KeyError), progress_bar("tracking", stream=tty):
        raise KeyError("no dataset")
    assert _lines(tty.getvalue())[-1].strip() == ""


def test_resumed_work_counts_from_where_it_resumed():
    tty = Terminal()
    with progress_bar("training", 100, unit="step", stream=tty) as bar:
        bar(91, 100)  # the first step after a checkpoint at 90
        assert bar._bar.initial == 90
        for k in range(92, 101):
            bar(k, 100)
    assert "100/100" in _lines(tty.getvalue())[-2]


def test_quiet_flag_before_or_after_the_subcommand(monkeypatch, tmp_path):
    import vslam.pipeline
    from vslam.cli import main
    from vslam.errors import ConfigError

    seen = []

    def fake_run(self, sequence=None, out_dir=None, progress=None):
        seen.append(progress.enabled)
        raise ConfigError("stop here")

    monkeypatch.setattr(vslam.pipeline.Pipeline, "run", fake_run)
    monkeypatch.setattr(sys, "stderr", Terminal())
    out = ["-o", str(tmp_path / "o")]
    for argv in (["run", *out], ["run", "-q", *out], ["-q", "run", *out], ["run", "--quiet", *out]):
        assert main(argv) == 2
    assert seen == [True, False, False, False]


def test_bench_jobs_report_each_job(monkeypatch):
    import vslam.bench.jobs
    from vslam.bench.batch import Job, run_jobs

    monkeypatch.setattr(vslam.bench.jobs, "run_job", lambda kind, config, over, out: {"ok": out})
    seen = []
    res = run_jobs([Job("slam", None, {}, f"j{i}") for i in range(3)], progress=lambda d, t: seen.append((d, t)))
    assert [r["ok"] for r in res] == ["j0", "j1", "j2"] and seen == [(1, 3), (2, 3), (3, 3)]


def test_vslam_run_in_a_terminal_shows_the_bar(tmp_path):
    """The real command in a pseudo-terminal (unsized, as `script` gives from a pipe): the bar's last line stays."""
    master, slave = pty.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("VSLAM_PROGRESS", "RANK")}
    root = Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = os.pathsep.join([str(root)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    small = [f"dataset.synthetic.{k}={v}" for k, v in (("width", 160), ("height", 120), ("fx", 131.25), ("fy", 131.25))]
    argv = ["run", "--max-frames", "15", "--no-eval", "-o", str(tmp_path / "run")]
    for kv in ("output.report=false", "tracker=baseline", *small):  # fast: the bar is what is tested
        argv += ["--set", kv]
    proc = subprocess.Popen([sys.executable, "-m", "vslam.cli", *argv],
                            stdin=slave, stdout=slave, stderr=slave, env=env, cwd=tmp_path, close_fds=True)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    assert proc.wait(timeout=120) == 0
    text = b"".join(chunks).decode(errors="replace").replace("\r\n", "\n")
    bar = [ln for ln in _lines(text) if ln.startswith("tracking:")]
    assert bar, text[-2000:]
    assert re.search(r"tracking: 100%.*15/15 \[\d\d:\d\d<00:00, +[\d.]+frame/s\]", bar[-1]), bar[-1]
