"""Progress bars: tqdm's bar on a terminal, a plain logged line every few seconds elsewhere."""

from __future__ import annotations

import io
import logging
import os
import pty

import pytest
from tqdm import tqdm

from fdnet.errors import ConfigError
from fdnet.logs import command_logging
from fdnet.progress import LineProgress, progress_bar


class Clock:
    """tqdm's clock, moved by hand (tqdm and LineProgress read the time through ``tqdm.std.time``)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _terminal() -> tuple[int, int]:
    """A pseudo-terminal of 24 x 100 (leader fd, follower fd): what tqdm sees on a real one."""
    import fcntl
    import struct
    import termios

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    return leader, follower


def _read_all(leader: int) -> str:
    """Everything written to the terminal so far (a pty hands it over in pieces); closes it."""
    import select

    chunks = []
    while select.select([leader], [], [], 0.5)[0]:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # EIO: the other end is closed and everything was read
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    return b"".join(chunks).decode()


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "fdnet.progress"]


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr("tqdm.std.time", clock)
    return clock


def test_off_a_terminal_a_line_at_most_every_interval_and_a_last_one(clock, caplog):
    caplog.set_level(logging.INFO, logger="fdnet")
    stream = io.StringIO()
    bar = progress_bar(total=100, desc="describe [x]", unit="img", file=stream, interval=10.0)
    assert isinstance(bar, LineProgress)
    for step in range(100):  # one update a second, 100 s in all
        clock.now += 1.0
        bar.set_postfix({"loss": f"{step:.3g}"}, refresh=False)
        bar.update(1)
        bar.set_description("joint")  # refreshes, which must not bypass the interval
    bar.close()
    lines = _lines(caplog)
    assert len(lines) == 10  # at 10, 20, ..., 100 s (the last one due at 100 s: close adds none)
    assert lines[0].startswith("joint: 10/100 img (10 %) [00:10<01:30, ") and lines[0].endswith("loss=9]")
    assert lines[-1].startswith("joint: 100/100 img (100 %)")
    assert stream.getvalue() == ""  # nothing of tqdm's own redraws reaches the stream


def test_a_task_shorter_than_the_interval_logs_nothing_and_close_adds_the_last_count(clock, caplog):
    caplog.set_level(logging.INFO, logger="fdnet")
    bar = progress_bar(total=5, desc="short", file=io.StringIO(), interval=10.0)
    clock.now += 3.0
    bar.update(5)
    bar.close()
    assert _lines(caplog) == []
    bar = progress_bar(range(30), desc="ORB features", unit="batch", file=io.StringIO(), interval=10.0)
    for _ in bar:
        clock.now += 0.5
    assert [line.split(" (")[0] for line in _lines(caplog)] == [
        "ORB features: 20/30 batch",
        "ORB features: 30/30 batch",
    ]


def test_on_a_terminal_it_is_tqdms_bar_redrawn_in_place():
    leader, follower = _terminal()
    with open(follower, "w", closefd=True) as terminal:
        bar = progress_bar(total=3, desc="describe", file=terminal, mininterval=0)
        assert type(bar) is tqdm
        for _ in range(3):
            bar.update(1)
        bar.close()
        terminal.flush()
    written = _read_all(leader)
    assert "\r" in written and "3/3" in written


def test_a_message_logged_during_a_bar_on_a_terminal_is_not_cut_by_it(monkeypatch):
    leader, follower = _terminal()
    with open(follower, "w", closefd=True) as terminal:
        monkeypatch.setattr("sys.stderr", terminal)
        with command_logging("train"):
            bar = progress_bar(total=3, mininterval=0)
            bar.update(1)
            logging.getLogger("fdnet.methods.calc.training").info("CALC: 12 training images")
            bar.update(2)
            bar.close()
        terminal.flush()
    written = _read_all(leader).replace("\r\n", "\n")
    # tqdm.write cleared the bar's line first: the message starts a line of its own
    line = next(part for part in written.split("\n") if "CALC" in part)
    assert line.split("\r")[-1] == "fdnet train: CALC: 12 training images"


def test_quiet_turns_bars_off_even_on_a_terminal(monkeypatch):
    leader, follower = _terminal()
    with open(follower, "w", closefd=True) as terminal:
        with command_logging("train", logging.WARNING):
            bar = progress_bar(total=3, file=terminal)
            bar.update(3)
            bar.close()
        assert bar.disable
    os.close(leader)


def test_the_interval_comes_from_the_environment(monkeypatch, clock, caplog):
    caplog.set_level(logging.INFO, logger="fdnet")
    monkeypatch.setenv("FDNET_PROGRESS_INTERVAL", "2.5")
    bar = progress_bar(total=10, file=io.StringIO())
    assert bar.interval == 2.5
    bar.close()
    for bad in ("0", "-1", "nan", "soon"):
        monkeypatch.setenv("FDNET_PROGRESS_INTERVAL", bad)
        with pytest.raises(ConfigError, match=f"FDNET_PROGRESS_INTERVAL={bad!r}: .*positive number"):
            progress_bar(total=10, file=io.StringIO())
