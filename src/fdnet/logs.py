"""Where the package's messages go when it runs as the ``fdnet`` command.

Library modules log through ``logging.getLogger(__name__)`` (all under the ``fdnet`` logger) and
never print. :func:`command_logging`, which :func:`fdnet.cli.main` wraps every command in, sends
those messages to standard error as ``fdnet COMMAND: message`` (``fdnet COMMAND: warning:
message`` for warnings), at level INFO, WARNING with ``--quiet``, DEBUG with ``--verbose``.
Standard output stays for what a command produces (tables, ``wrote ...`` lines, its summary).

A program that imports ``fdnet`` configures ``logging`` as it likes; configured nothing, it sees
the warnings only (Python's default).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from typing import Iterator

#: the logger every module of the package logs under
PACKAGE_LOGGER = "fdnet"
#: seconds between two progress lines when standard error is not a terminal (:mod:`fdnet.progress`)
LINE_INTERVAL_S = 10.0
#: the environment variable that sets another interval
INTERVAL_VARIABLE = "FDNET_PROGRESS_INTERVAL"


class StderrHandler(logging.Handler):
    """Writes each record as one line to ``sys.stderr`` as it is when the record comes (a
    redirected or captured stream included). On a terminal with tqdm bars running, through
    ``tqdm.write``, which clears the bars, writes the line and redraws them below it, so a
    message does not cut a bar in two."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = self.format(record)
            stream = sys.stderr
            tqdm_module = sys.modules.get("tqdm")  # bars exist only where tqdm was imported
            if tqdm_module is not None and is_terminal(stream):
                tqdm_module.tqdm.write(message, file=stream)
            else:
                stream.write(message + "\n")
                stream.flush()
        except Exception:  # noqa: BLE001 (logging's own contract: a failing handler reports, never raises)
            self.handleError(record)


class CommandFormatter(logging.Formatter):
    """``fdnet COMMAND: message``, ``fdnet COMMAND: warning: message`` at WARNING and above (the
    CLI's own errors read ``fdnet COMMAND: error: ...``)."""

    def __init__(self, command: str) -> None:
        super().__init__()
        self.prefix = f"fdnet {command}: " if command else "fdnet: "

    def formatMessage(self, record: logging.LogRecord) -> str:  # noqa: N802 (logging's name)
        level = "warning: " if record.levelno >= logging.WARNING else ""
        return self.prefix + level + record.getMessage()


def is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def line_interval() -> float:
    """Seconds between two progress lines off a terminal: ``FDNET_PROGRESS_INTERVAL`` when set
    (a positive number), else :data:`LINE_INTERVAL_S`."""
    import math

    from fdnet.errors import ConfigError

    text = os.environ.get(INTERVAL_VARIABLE, "").strip()
    if not text:
        return LINE_INTERVAL_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(
            f"{INTERVAL_VARIABLE}={text!r}: give the seconds between two progress lines, " "a positive number (e.g. 30)"
        )
    return value


def level_for(quiet: bool = False, verbose: bool = False) -> int:
    """The ``fdnet`` logger's level for the ``--quiet``/``--verbose`` flags."""
    if quiet:
        return logging.WARNING
    return logging.DEBUG if verbose else logging.INFO


@contextlib.contextmanager
def command_logging(command: str, level: int = logging.INFO) -> Iterator[logging.Handler]:
    """For the block: the ``fdnet`` logger at ``level``, writing to standard error through a
    :class:`StderrHandler` with a :class:`CommandFormatter`. Handler and level are removed and
    restored afterwards, so a process that runs several commands (the tests) does not collect
    handlers; a command run inside another (``fdnet demo`` runs ``fdnet train``) reuses the
    outer one's handler with its own prefix. Records still propagate to the root logger's
    handlers (a program's own, pytest's capture)."""
    line_interval()  # a bad FDNET_PROGRESS_INTERVAL stops the command before any work
    logger = logging.getLogger(PACKAGE_LOGGER)
    outer = next((h for h in logger.handlers if isinstance(h, StderrHandler)), None)
    handler = outer or StderrHandler()
    previous_formatter, previous_level = handler.formatter, logger.level
    handler.setFormatter(CommandFormatter(command))
    if outer is None:
        logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield handler
    finally:
        logger.setLevel(previous_level)
        if outer is None:
            logger.removeHandler(handler)
        else:
            handler.setFormatter(previous_formatter)
