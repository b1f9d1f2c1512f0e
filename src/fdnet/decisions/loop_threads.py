"""Threads for one frame's work: what the loop-closure detector does per frame is small for
several threads to pay for their synchronisation, and on cores shared with other work a
descheduled thread stalls the others; so search runs on one thread and describing on as many as
measure faster."""

from __future__ import annotations

import contextlib
import sys
import time

import numpy as np

from fdnet.backbones import torch_threads

_BLAS = None


def single_blas_thread():
    """A context in which numpy's BLAS runs one thread (threadpoolctl, the controller made once:
    making it per frame would cost more than the product). One row against the map is a
    memory-bound matrix-vector product: BLAS threads only add synchronisation, and on shared
    cores they made it ~5x slower (17 ms vs 3.7 ms for 3000 x 2048 on the 2-core machine of
    docs/loop-closure.md)."""
    global _BLAS
    if _BLAS is None:
        from threadpoolctl import ThreadpoolController

        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


class FrameThreads:
    """The torch threads that describe one frame, chosen by measuring: one, or the process's own
    count (``own``, torch's when made), whichever described the recent frames faster. Why measure:
    on idle cores two threads describe one FDNet frame in 7.4 ms against 9-10 on one (`fdnet
    benchmark --parts api`, one image a call), while on cores shared with other work a descheduled
    thread stalls the other at every layer (on 2 loaded cores: 6.7 frames/s with 2 threads, 47 with
    1; docs/loop-closure.md). Neither suits every machine, and a robot's load changes as it runs.

    It starts on one thread. Every ``every`` frames it describes one frame on the other count; when
    the other count's recent frames (at least :attr:`MIN_PROBES`) have a median under
    :attr:`MARGIN` of the current count's, it switches. A probe that loses doubles the spacing (to
    :attr:`MAX_EVERY` frames), so a loaded machine pays a stalled frame rarely. ``fixed``: always
    that many threads (reproducible to the bit: FDNet's vectors on one and two threads differ by
    up to 4e-7)."""

    MIN_PROBES = 3
    MARGIN = 0.9
    FIRST_EVERY = 4
    MAX_EVERY = 256
    WINDOW = 9

    def __init__(self, fixed: int | None = None, own: int | None = None):
        from collections import deque

        if own is None:
            torch = sys.modules.get("torch")
            own = torch.get_num_threads() if torch is not None else 1
        self.fixed = fixed
        self.counts = (1, max(1, int(own)))
        self.current = 1
        self.every = self.FIRST_EVERY
        self._since_probe = 0
        self._seconds = {count: deque(maxlen=self.WINDOW) for count in self.counts}
        self.clock = time.perf_counter
        #: frames described so far, per thread count
        self.used: dict[int, int] = {}

    def run(self, describe):
        """``describe()`` on the count :meth:`next` gives, timed by :attr:`clock` and recorded."""
        count = self.next()
        start = self.clock()
        # a descriptor without torch never loads it
        with torch_threads(count) if "torch" in sys.modules else contextlib.nullcontext():
            result = describe()
        self.record(count, self.clock() - start)
        self.used[count] = self.used.get(count, 0) + 1
        return result

    def next(self) -> int:
        """The thread count for the next frame."""
        if self.fixed is not None:
            return int(self.fixed)
        if self.counts[1] == 1:
            return 1
        self._since_probe += 1
        if self._since_probe >= self.every:
            self._since_probe = 0
            return self._other()
        return self.current

    def record(self, count: int, seconds: float) -> None:
        """How long a frame on ``count`` threads took to describe."""
        if self.fixed is not None or count not in self._seconds:
            return
        self._seconds[count].append(float(seconds))
        other = self._other()
        if count != other or len(self._seconds[other]) < self.MIN_PROBES:
            return
        if float(np.median(self._seconds[other])) < self.MARGIN * float(np.median(self._seconds[self.current])):
            self.current, self.every = other, self.FIRST_EVERY
        else:
            self.every = min(2 * self.every, self.MAX_EVERY)

    def _other(self) -> int:
        return self.counts[1] if self.current == self.counts[0] else self.counts[0]
