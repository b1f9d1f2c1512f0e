"""Where messages go when fdnet runs as a command: standard error, ``fdnet COMMAND: ...``;
--quiet/--verbose; progress off a terminal as a bounded number of plain lines."""

from __future__ import annotations

import contextlib
import io
import logging
import re
import time

import pytest

from fdnet.cli import main
from fdnet.errors import ConfigError
from fdnet.logs import StderrHandler, command_logging, level_for

from conftest import write_day_night_set

PROGRESS_LINE = re.compile(r"^fdnet train: (autoencoder|critic|joint): \d+/\d+ step \(\d+ %\) \[")


def _handlers() -> list:
    return [h for h in logging.getLogger("fdnet").handlers if isinstance(h, StderrHandler)]


def test_messages_go_to_standard_error_with_the_commands_name(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr("sys.stderr", err)
    with command_logging("evaluate"):
        logging.getLogger("fdnet.descriptors.dbow").warning("dbow: no vocabulary given")
        logging.getLogger("fdnet.reproduce.runner").info("[comparison] done in %.1f s", 2.04)
        logging.getLogger("fdnet.reproduce.runner").debug("not shown at INFO")
        logging.getLogger("elsewhere").warning("another package's logger is not ours to format")
    assert err.getvalue() == (
        "fdnet evaluate: warning: dbow: no vocabulary given\n" "fdnet evaluate: [comparison] done in 2.0 s\n"
    )


def test_levels_and_the_handler_last_as_long_as_the_command(monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    logger = logging.getLogger("fdnet")
    before = (logger.level, _handlers())
    with command_logging("train", level_for(quiet=True)):
        assert logger.level == logging.WARNING and len(_handlers()) == 1
        with command_logging("train", level_for(verbose=True)):  # fdnet demo runs fdnet train
            assert logger.level == logging.DEBUG and len(_handlers()) == 1  # one handler, not two
            assert _handlers()[0].formatter.prefix == "fdnet train: "
        assert logger.level == logging.WARNING
    assert (logger.level, _handlers()) == before
    assert level_for() == logging.INFO


def test_a_bad_progress_interval_stops_the_command_before_any_work(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("FDNET_PROGRESS_INTERVAL", "-3")
    with pytest.raises(ConfigError, match="FDNET_PROGRESS_INTERVAL='-3'"):
        with command_logging("train"):
            pass
    assert main(["synth", "--out", str(tmp_path / "route"), "--num-frames", "4"]) == 2
    assert "fdnet synth: error: FDNET_PROGRESS_INTERVAL='-3'" in capsys.readouterr().err
    assert not (tmp_path / "route").exists()


def _dataset(root, n=8):
    return write_day_night_set(root, n)


def _train_into_a_file(tmp_path, name: str, *flags: str) -> tuple[str, float]:
    """``fdnet train --preset tiny`` with standard output and error redirected to one file, as
    ``fdnet train ... > log 2>&1`` does: (what the file holds, seconds the command took)."""
    log = tmp_path / f"{name}.log"
    argv = ["train", "--data", str(tmp_path / "data"), "--preset", "tiny", "--out", str(tmp_path / name), *flags]
    with open(log, "w") as file, contextlib.redirect_stdout(file), contextlib.redirect_stderr(file):
        started = time.monotonic()
        assert main(argv) == 0
        seconds = time.monotonic() - started
    return log.read_text(), seconds


def test_train_into_a_log_file_writes_lines_not_redraws(tmp_path, monkeypatch):
    from fdnet.methods.fdnet.training import FDNetTraining

    _dataset(tmp_path / "data")
    interval = 0.25
    monkeypatch.setenv("FDNET_PROGRESS_INTERVAL", str(interval))
    step = FDNetTraining.train_step

    def slow_step(self, index):  # 8 steps of at least 0.1 s: longer than a few intervals
        time.sleep(0.1)
        return step(self, index)

    monkeypatch.setattr(FDNetTraining, "train_step", slow_step)
    text, seconds = _train_into_a_file(tmp_path, "run")
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert lines[0].startswith("fdnet train: preset tiny, conditions day, night (8, 8 images)")
    assert lines[-1].startswith("fdnet train: finished at step 8/8")
    progress = [line for line in lines if PROGRESS_LINE.match(line)]
    # at least one line on the way and the last count; at most one per interval and the last
    assert progress[-1].startswith("fdnet train: joint: 8/8 step (100 %)")
    assert 2 <= len(progress) <= seconds / interval + 1
    assert len(lines) == len(progress) + 2  # nothing else: no bar, no blank or partial lines

    quiet, _ = _train_into_a_file(tmp_path, "quiet", "--quiet")
    assert quiet.splitlines() == [next(line for line in quiet.splitlines() if "finished at step 8/8" in line)]
