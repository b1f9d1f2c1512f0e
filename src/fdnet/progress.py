"""Progress bars: tqdm's bar on a terminal, a plain line every few seconds anywhere else.

Every progress bar of the package comes from :func:`progress_bar`. On a terminal it is tqdm's
ordinary bar, redrawn in place. When the stream is not a terminal (a log file, a pipe, a job
scheduler's output) tqdm's in-place redraws would be thousands of carriage-return updates in
one line of the file; there the bar is a :class:`LineProgress` instead, which logs one plain line
(logger ``fdnet.progress``, level INFO) at most every :data:`LINE_INTERVAL_S` seconds and a final
line when it closes (``FDNET_PROGRESS_INTERVAL`` sets another interval). A task that ends within
the first interval logs nothing.

``--quiet`` (the ``fdnet`` logger set above INFO) turns bars off on a terminal too.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, Iterable

from tqdm import tqdm

from fdnet.logs import LINE_INTERVAL_S, PACKAGE_LOGGER, is_terminal, line_interval

log = logging.getLogger(__name__)

#: the line a :class:`LineProgress` logs (tqdm's meter without the bar graphic, which means
#: nothing in a file)
LINE_FORMAT = "{n_fmt}/{total_fmt} {unit} ({percentage:.0f} %) [{elapsed}<{remaining}, {rate_fmt}{postfix}]"
#: the same without a known total
LINE_FORMAT_NO_TOTAL = "{n_fmt} {unit} [{elapsed}, {rate_fmt}{postfix}]"


def quiet() -> bool:
    """Whether the command was asked for warnings only (``--quiet``): the ``fdnet`` logger's own
    level is above INFO. A library caller who configured nothing keeps its bars."""
    level = logging.getLogger(PACKAGE_LOGGER).level
    return level != logging.NOTSET and level > logging.INFO


def progress_bar(
    iterable: Iterable | None = None,
    *,
    total: float | None = None,
    desc: str = "",
    unit: str = "it",
    initial: float = 0,
    leave: bool = True,
    file=None,
    interval: float | None = None,
    **tqdm_options: Any,
):
    """A tqdm progress bar over ``iterable`` (or counting to ``total`` by ``update``) on ``file``
    (default: standard error). On a terminal: tqdm's bar (``dynamic_ncols``), with
    ``tqdm_options`` passed on. Elsewhere: a :class:`LineProgress` logging a line at most every
    ``interval`` seconds (default :func:`fdnet.logs.line_interval`: ``FDNET_PROGRESS_INTERVAL``
    or :data:`LINE_INTERVAL_S`). Under ``--quiet``: a disabled bar
    (same methods, no output)."""
    stream = sys.stderr if file is None else file
    if quiet():
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, disable=True)
    if is_terminal(stream):
        tqdm_options.setdefault("dynamic_ncols", True)
        return tqdm(
            iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave, file=stream, **tqdm_options
        )
    smoothing = tqdm_options.get("smoothing", 0.3)
    return LineProgress(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        initial=initial,
        file=stream,
        smoothing=smoothing,
        interval=line_interval() if interval is None else interval,
    )


class LineProgress(tqdm):
    """A tqdm bar that never redraws: it logs ``"DESC: n/total unit (p %) [elapsed<left,
    rate, postfix]"`` through :data:`log`, at most every ``interval`` seconds, and a last line
    on close when it logged any before and has moved since. Nothing is written to ``file``
    itself. tqdm's documented way to change the output is to override :meth:`display`; its
    own throttles (``mininterval``, ``delay``) hold back the update checks, and
    :meth:`display` keeps the interval also against ``refresh()`` calls that bypass them
    (``set_description``, ``set_postfix``)."""

    def __init__(self, *args, interval: float = LINE_INTERVAL_S, **kwargs) -> None:
        self.interval = float(interval)
        self.lines = 0
        self._last_line_t = None
        self._last_line_n = None
        # miniters=1: check the clock on every update (never skip a due line after a slow
        # stretch); delay: no line at the start; leave=False: close() itself adds nothing.
        super().__init__(
            *args, mininterval=self.interval, miniters=1, delay=self.interval, leave=False, ascii=True, **kwargs
        )

    def _line(self) -> str:
        fmt = dict(self.format_dict)
        fmt["bar_format"] = LINE_FORMAT if self.total else LINE_FORMAT_NO_TOTAL
        fmt["prefix"] = ""
        meter = self.format_meter(**fmt)
        desc = self.desc[:-2] if self.desc.endswith(": ") else self.desc  # set_description adds ": "
        return f"{desc}: {meter}" if desc else meter

    def display(self, msg=None, pos=None) -> bool:
        if msg is not None:  # tqdm clearing its line ('' on close or before a write): nothing to clear
            return False
        now = self._time()
        started = getattr(self, "start_t", None)  # None while tqdm's __init__ runs
        if started is None or now < started + self.interval:
            return False
        if self._last_line_t is not None and now - self._last_line_t < self.interval:
            return False
        self._emit(now)
        return True

    def _emit(self, now: float) -> None:
        log.info(self._line())
        self.lines += 1
        self._last_line_t, self._last_line_n = now, self.n

    def clear(self, nolock: bool = False) -> None:
        pass  # tqdm.write() clears bars before writing; a line in a log needs no clearing

    def close(self) -> None:
        if not self.disable and self.lines and self.n != self._last_line_n:
            self._emit(self._time())
        super().close()
