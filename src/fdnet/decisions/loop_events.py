"""Loop-closure events on disk: each accepted closure is one line of a CSV (and of JSON lines),
written and synced as it is accepted (:class:`EventLog`)."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Sequence

from fdnet.decisions.loop_records import EVENT_COLUMNS, Closure
from fdnet.errors import ConfigError, DataError, output_error
from fdnet.io import spreadsheet_text


class EventLog:
    """Accepted closures written as they happen: a CSV (header :data:`EVENT_COLUMNS`) and,
    optionally, JSON lines with the same keys.

    Guarantee: both files are created fresh when the log opens (the header written atomically,
    :func:`fdnet.io.atomic_write_text`); when :meth:`write` returns, the event's line is on disk
    in each file (the whole line in one ``os.write`` on an ``O_APPEND`` descriptor, then
    ``fsync``). A crash or ``kill -9`` therefore leaves every event reported before it, each line
    complete; only a power cut in the middle of a write can leave one incomplete last line (no
    final newline), which readers drop. One fsync per accepted closure, not per frame.
    """

    def __init__(
        self, csv_path: str | os.PathLike, jsonl_path: str | os.PathLike | None = None, initial: Sequence[Closure] = ()
    ):
        from fdnet.io import atomic_write_text

        self.paths = [Path(csv_path)] + ([Path(jsonl_path)] if jsonl_path is not None else [])
        if len({p.resolve() for p in self.paths}) != len(self.paths):
            raise ConfigError(f"{csv_path}: the CSV and the JSON-lines events must be two different files")
        self._fds: list[int] = []
        # A resumed run starts the files again from the events its replay re-derived (the same
        # decisions as the interrupted run's), atomically: no event twice, none lost, and no
        # half line a crash may have left.
        lines = [self._lines(closure) for closure in initial]
        atomic_write_text(self.paths[0], self._csv_line(EVENT_COLUMNS) + "".join(line[0] for line in lines))
        if jsonl_path is not None:
            atomic_write_text(self.paths[1], "".join(line[1] for line in lines))
        try:
            for path in self.paths:
                self._fds.append(os.open(path, os.O_WRONLY | os.O_APPEND))
        except OSError as exc:
            self.close()
            raise DataError(f"cannot open the events file for appending ({exc.strerror or exc})") from exc
        self.count = len(lines)

    @staticmethod
    def _csv_line(values) -> str:
        buffer = io.StringIO()
        csv.writer(buffer, lineterminator="\n").writerow(values)
        return buffer.getvalue()

    def _lines(self, closure: Closure) -> tuple[str, str]:
        """The event's CSV line and JSON line."""
        event = closure.to_dict()
        cells = [
            ""
            if event[c] is None
            else (
                f"{event[c]:.6f}"
                if isinstance(event[c], float)
                else spreadsheet_text(event[c])
                if c in ("query", "match")
                else event[c]
            )
            for c in EVENT_COLUMNS
        ]
        return self._csv_line(cells), json.dumps({c: event[c] for c in EVENT_COLUMNS}, allow_nan=False) + "\n"

    def write(self, closure: Closure) -> None:
        lines = self._lines(closure)
        sizes = [os.fstat(fd).st_size for fd in self._fds]
        for fd, line, path in zip(self._fds, lines, self.paths):
            data = line.encode("utf-8", "surrogateescape")  # a name that is not UTF-8: its own bytes
            try:
                # a full disk stops a write short; writing the rest then says why (ENOSPC)
                done = 0
                while done < len(data):
                    done += os.write(fd, data[done:])
                os.fsync(fd)
            except OSError as exc:
                # no half line, and no event in one file that the other lacks: every file ends at
                # the last whole event acknowledged, as before this write
                for other, size in zip(self._fds, sizes):
                    try:
                        os.ftruncate(other, size)
                    except OSError:
                        pass
                raise output_error(
                    f"{path}: cannot write the loop-closure event ({exc.strerror or exc}); every "
                    "events file ends at the last whole event",
                    exc,
                ) from exc
        self.count += 1

    def close(self) -> None:
        while self._fds:
            os.close(self._fds.pop())

    def __enter__(self) -> "EventLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
