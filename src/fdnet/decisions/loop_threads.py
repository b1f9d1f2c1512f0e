"""One thread for one frame's work: what the loop-closure detector does per frame is too small
for several threads to pay for their synchronisation, and on cores shared with other work a
descheduled thread stalls the others."""

from __future__ import annotations

import sys

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


class single_torch_thread:
    """torch on one intra-op thread while one frame is described: a single image gives each of
    several threads too little work to pay for their barriers, and on cores shared with other
    work a descheduled thread stalls the others at every layer (measured on 2 loaded cores: 6.7
    frames/s with 2 threads, 47 with 1; docs/loop-closure.md)."""

    def __enter__(self):
        self._torch = sys.modules.get("torch")  # a descriptor without torch never loads it
        if self._torch is not None:
            self._threads = self._torch.get_num_threads()
            if self._threads != 1:
                self._torch.set_num_threads(1)

    def __exit__(self, *exc):
        if self._torch is not None and self._threads != 1:
            self._torch.set_num_threads(self._threads)
