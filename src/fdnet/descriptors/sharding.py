"""One image list described by several processes started by ``torchrun``: ``fdnet extract`` and
``fdnet database build`` on many GPUs or machines.

``torchrun --nproc-per-node N [--nnodes M --node-rank K --rdzv-endpoint HOST:PORT] -m fdnet extract ...``
starts N processes per machine; each reads ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK`` and
``LOCAL_WORLD_SIZE`` from its environment (:meth:`Shards.from_env`). Without ``WORLD_SIZE``, or with
``WORLD_SIZE=1``, nothing here changes anything: a plain command runs as it always did.

**Split.** Every process lists the same images in the one order and describes its contiguous
block of them (:meth:`Shards.block`: process r of W takes ``r*N//W`` to ``(r+1)*N//W``) on its own
GPU (``cuda:LOCAL_RANK`` becomes the current device, so ``--device auto``/``cuda`` mean it) or on
the CPU (the machine's cores divided among its processes). First the processes compare the images'
number, absolute paths, sizes and modification times and the model's fingerprint
(:func:`check_same_inputs`).

**Transport.** Rank 0 writes the one output file. Its block comes first, so it writes its vectors
as they are made; every other process spools its own to a temporary file on its machine
(:class:`~fdnet.descriptors.pipeline.VectorSpool` under ``TMPDIR/fdnet-shards-UID``: machines
share no file system but the images') and, once every block is described, sends them to rank 0 in
chunks of :data:`CHUNK_BYTES`, rank by rank, through ``torch.distributed``'s gloo backend on CPU
tensors (the vectors are on the CPU by then; NCCL would add a backend and save nothing). No process
holds more than its batches and one chunk.

**Lockstep and failures.** Every process enters every collective in the same order: an all-reduce
of an error flag after each batch (a process out of batches still takes part) and before each
chunk sent. A process that fails (an unreadable image, a full disk) raises its own error, the others
:class:`OtherProcessFailed` naming it, at the same step: one line each, never a hang. A process that
dies (``kill -9``) closes its connections: the others' next collective fails with
:class:`ShardingError`, as does torchrun's SIGTERM, so ``with`` blocks run and rank 0 removes its
parts (a killed rank 0's, or another's spool, is removed by the next run there, as for one
process). Collectives time out after :data:`TIMEOUT`.

**Learning from images.** A method that learns from the images it describes (``needs_fit``:
dbow without a vocabulary, trunk-whitened without ``--fit``) learns on rank 0 from all of them;
the attributes ``fit`` set are broadcast, and the fingerprint check confirms one model.

**Test hook.** ``FDNET_TEST_KILL_RANK=RANK:BATCHES`` (read only here): process RANK SIGKILLs itself
after BATCHES batches, how the tests kill one mid-run. Never set it otherwise.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
import signal
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence, TypeVar

import numpy as np

from fdnet.errors import ConfigError, FdnetError
from fdnet.torchrun import environment_int, leave, quiet_unless, require_rendezvous

log = logging.getLogger(__name__)

T = TypeVar("T")

#: how long a collective waits for the slowest process (the longest wait: rank 0 fitting a method)
TIMEOUT = datetime.timedelta(minutes=30)
#: bytes of vectors sent to rank 0 at a time
CHUNK_BYTES = 16 << 20
#: the test hook's environment variable (module docstring)
KILL_VARIABLE = "FDNET_TEST_KILL_RANK"


class ShardingError(FdnetError):
    """The processes lost contact (one died, or torchrun stopped them), or the launch is unusable."""


class OtherProcessFailed(FdnetError):
    """Raised on the processes that did not fail themselves when another one failed."""


def _backend_message(exc: BaseException) -> str:
    """A gloo error's first sentence without its source location ("Connection closed by peer ...")."""
    import re

    text = re.sub(r"\[[^\]]*\.(cc|cpp|h):\d+\]\s*", "", " ".join(str(exc).split()))
    return (text.split(". ")[0] or type(exc).__name__)[:300]


def _one_line(exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, FdnetError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split())


class Shards:
    """This process's place among ``world_size`` processes describing one image list (module
    docstring). ``rank`` 0 writes the output; ``local_rank`` is the process's index on its
    machine (its GPU). Until :meth:`init` (and always for one process) every collective below
    returns at once with this process's own value."""

    def __init__(self, world_size: int = 1, rank: int = 0, local_rank: int = 0, local_world_size: int = 1):
        if world_size < 1 or not 0 <= rank < world_size or local_rank < 0 or local_world_size < 1:
            raise ConfigError(f"invalid torchrun setup: RANK={rank}, LOCAL_RANK={local_rank}, "
                              f"WORLD_SIZE={world_size}, LOCAL_WORLD_SIZE={local_world_size}")
        self.world_size = int(world_size)
        self.rank = int(rank)
        self.local_rank = int(local_rank)
        self.local_world_size = int(local_world_size)
        self.enabled = False
        self._owns_group = False

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "Shards":
        """torchrun's ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``; one process
        when ``WORLD_SIZE`` is absent or 1."""
        environ = os.environ if environ is None else environ
        if "WORLD_SIZE" not in environ or environment_int(environ, "WORLD_SIZE") == 1:
            return cls()
        world_size = environment_int(environ, "WORLD_SIZE")
        return cls(world_size, environment_int(environ, "RANK"), environment_int(environ, "LOCAL_RANK", 0),
                   environment_int(environ, "LOCAL_WORLD_SIZE", 1))

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes the output."""
        return self.rank == 0

    def block(self, count: int, rank: int | None = None) -> tuple[int, int]:
        """``(start, end)`` of process ``rank``'s (default: this one's) block of ``count`` items: the
        blocks of ranks 0..W-1 follow each other and differ in size by at most one."""
        rank = self.rank if rank is None else int(rank)
        return rank * count // self.world_size, (rank + 1) * count // self.world_size

    def threads(self) -> int | None:
        """torch CPU threads: the machine's cores divided among its processes (None: one process)."""
        if self.world_size == 1:
            return None
        return max(1, (os.cpu_count() or 1) // self.local_world_size)

    # ------------------------------------------------------------------ set-up
    def init(self) -> "Shards":
        """Join the process group (gloo; a no-op for one process), after making ``cuda:LOCAL_RANK``
        this process's current CUDA device on a machine with GPUs."""
        import torch

        if self.world_size == 1 or self.enabled:
            return self
        if torch.cuda.is_available() and self.local_rank < torch.cuda.device_count():
            torch.cuda.set_device(self.local_rank)
        import torch.distributed as dist

        if not dist.is_available() or not dist.is_gloo_available():
            raise ConfigError("this torch build has no torch.distributed with gloo; describing images in "
                              "several processes needs it")
        if dist.is_initialized():  # the caller's own process group: used, left to the caller to destroy
            if dist.get_world_size() != self.world_size:
                raise ConfigError(f"WORLD_SIZE={self.world_size} but the running process group has "
                                  f"{dist.get_world_size()} processes")
            self.enabled = True
            return self
        require_rendezvous(os.environ, self.world_size)
        self._call("joining the other processes",
                   lambda: dist.init_process_group("gloo", init_method="env://", world_size=self.world_size,
                                                   rank=self.rank, timeout=TIMEOUT))
        self.enabled = self._owns_group = True
        torch.set_num_threads(self.threads())
        return self

    def destroy(self) -> None:
        if self.enabled and self._owns_group:
            import torch.distributed as dist

            with contextlib.suppress(Exception):  # after a lost process it may fail too: nothing to save
                dist.destroy_process_group()
        self.enabled = self._owns_group = False

    def check_device(self, device) -> None:
        """ConfigError unless a CUDA ``device`` is this process's own GPU, ``cuda:LOCAL_RANK``."""
        if device is None or not self.enabled:
            return
        import torch

        device = torch.device(device)
        if device.type != "cuda":
            return
        count = torch.cuda.device_count()
        if self.local_rank >= count:
            raise ConfigError(f"process {self.rank} (LOCAL_RANK {self.local_rank}) has no GPU of its own: this "
                              f"machine has {count} GPU(s) and each process describes on cuda:LOCAL_RANK; start at "
                              f"most {count} processes per machine (torchrun --nproc-per-node {count}) or use "
                              "--device cpu")
        if device.index is not None and device.index != self.local_rank:
            raise ConfigError(f"--device {device} for process {self.rank}: under torchrun each process describes on "
                              f"its own GPU, cuda:LOCAL_RANK (here cuda:{self.local_rank}); give --device cuda or "
                              "auto, not cuda:N")

    # ------------------------------------------------------------------ collectives
    def _call(self, what: str, fn: Callable[[], T]) -> T:
        """``fn()``, a torch.distributed call: a lost process becomes one line, not a traceback."""
        try:
            return fn()
        except RuntimeError as exc:  # gloo: connection closed or reset by a peer, a timeout
            raise ShardingError(f"process {self.rank} of {self.world_size} lost contact with the others while "
                                f"{what} (another process stopped or was killed; its error, if any, is above): "
                                f"{_backend_message(exc)}") from None

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` is true in any process (one small all-reduce)."""
        if not self.enabled:
            return bool(flag)
        import torch
        import torch.distributed as dist

        tensor = torch.tensor([1 if flag else 0], dtype=torch.int32)
        self._call("agreeing on errors", lambda: dist.all_reduce(tensor, op=dist.ReduceOp.MAX))
        return bool(tensor.item())

    def gather(self, obj) -> list:
        """Every process's ``obj``, in rank order, in every process."""
        if not self.enabled:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world_size
        self._call("exchanging settings", lambda: dist.all_gather_object(out, obj))
        return out

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` in every process (pickled)."""
        if not self.enabled:
            return obj
        import torch.distributed as dist

        box = [obj if self.is_main else None]
        self._call("receiving rank 0's settings", lambda: dist.broadcast_object_list(box, src=0))
        return box[0]

    def stop_if_failed(self, error: BaseException | None) -> None:
        """Called by every process at the same point with its error or None: when any had one, the
        failing ones raise theirs, the others :class:`OtherProcessFailed` naming the first."""
        if not self.enabled:
            if error is not None:
                raise error
            return
        if not self.any(error is not None):
            return
        messages = self.gather(None if error is None else _one_line(error))
        if error is not None:
            raise error
        rank, message = next((r, m) for r, m in enumerate(messages) if m is not None)
        raise OtherProcessFailed(f"stopped because process {rank} of {self.world_size} failed: {message}")

    def collectively(self, fn: Callable[[], T], main_only: bool = False) -> T:
        """``fn()`` (no collective inside) in every process, or in rank 0 alone (``main_only``: its
        result broadcast), every process stopping when it fails in any (:meth:`stop_if_failed`)."""
        if not self.enabled:
            return fn()
        result, error = None, None
        if not main_only or self.is_main:
            try:
                result = fn()
            except Exception as exc:  # noqa: BLE001 - raised below, in every process
                error = exc
        self.stop_if_failed(error)
        return self.broadcast(result) if main_only else result

    # ------------------------------------------------------------------ output
    def quiet_unless_main(self):
        """One process reports (:func:`fdnet.torchrun.quiet_unless`)."""
        return quiet_unless(self.is_main)


_SINGLE = Shards()
_current: Shards = _SINGLE


def current() -> Shards:
    """The running launch's :class:`Shards` (a single process outside :func:`launch`)."""
    return _current


def refuse_under_torchrun(what: str, environ: Mapping[str, str] | None = None) -> None:
    """ConfigError when ``what``, a one-process command, was started as several by torchrun."""
    if Shards.from_env(environ).world_size > 1:
        raise ConfigError(f"{what} runs in one process; torchrun is for fdnet extract and fdnet database build")


@contextlib.contextmanager
def launch(environ: Mapping[str, str] | None = None, command: bool = False) -> Iterator[Shards]:
    """Join the processes the environment describes for the block, make them :func:`current`, stop
    on SIGTERM with an error and quiet all but rank 0; one process gets a no-op context, a nested
    launch the running one. ``command``: an fdnet command, whose process, having joined a group,
    leaves by ``os._exit`` once its exit handlers ran (:func:`exit_process`)."""
    global _current
    if _current is not _SINGLE:
        yield _current
        return
    shards = Shards.from_env(environ)
    if shards.world_size == 1:
        yield shards
        return
    shards.init()
    _current = shards
    restore = _stop_on_sigterm()
    code = 0
    try:
        with shards.quiet_unless_main():
            yield shards
    except BaseException as exc:
        code = _exit_code(exc)
        raise
    finally:
        restore()
        _current = _SINGLE
        shards.destroy()
        if command:
            _exit_after_handlers(code)


def _stop_on_sigterm() -> Callable[[], None]:
    """SIGTERM (torchrun stopping every process, one having failed) raises ShardingError here, so
    ``with`` blocks remove their files (forked decoding workers just end). Returns the undo."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    owner = os.getpid()

    def stop(signum, frame):
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        raise ShardingError("stopped by SIGTERM: torchrun stops every process when one of them fails or is "
                            "killed (its error, if any, is above)")

    previous = signal.signal(signal.SIGTERM, stop)
    return lambda: signal.signal(signal.SIGTERM, previous)


def _exit_code(exc: BaseException) -> int:
    """``fdnet``'s exit status for ``exc`` (:func:`fdnet.cli.main`): 130, 2 (one line) or 1 (a bug)."""
    if isinstance(exc, KeyboardInterrupt):
        return 130
    if isinstance(exc, SystemExit):
        return exc.code if isinstance(exc.code, int) else 1
    if isinstance(exc, (FdnetError, OSError, MemoryError)):
        return 2
    return 1


_exit_hook: Callable[[], None] | None = None


def _exit_after_handlers(code: int) -> None:
    """At exit (the command line has printed its result or error), run the exit handlers and leave
    by ``os._exit(code)``: a gloo process's native threads, torn down at interpreter exit, now and
    then die of ``std::terminate`` (SIGABRT) after the work is done (as training found)."""
    import atexit

    global _exit_hook
    if _exit_hook is not None:
        atexit.unregister(_exit_hook)

    def hook() -> None:
        exit_process(code)

    _exit_hook = hook
    atexit.register(hook)


def exit_process(code: int) -> None:
    """End this process with ``code`` by :func:`fdnet.torchrun.leave` (exit handlers, flushed
    output, ``os._exit``), its pending exit hook taken out first."""
    import atexit

    global _exit_hook
    if _exit_hook is not None:
        atexit.unregister(_exit_hook)
        _exit_hook = None
    leave(code)


# ---------------------------------------------------------------------- the work
def check_same_inputs(shards: Shards, paths: Sequence, descriptor) -> None:
    """ConfigError in every process unless all of them list the same images (by content:
    :func:`fdnet.data.identity.images_digest`, each image's absolute path, size and modification
    time, in order) and hold the same model (its fingerprint). Two folders whose images share
    file names are two image lists."""
    if not shards.enabled:
        return
    from fdnet.data.identity import describe_facts, image_facts, images_digest

    mine = shards.collectively(lambda: (len(paths), images_digest(paths), descriptor.fingerprint(),
                                        int(descriptor.dim)))
    everyone = shards.gather(mine)
    first = everyone[0]
    for rank, theirs in enumerate(everyone[1:], start=1):
        if theirs[0] != first[0]:
            raise ConfigError(f"process {rank} of {shards.world_size} lists {theirs[0]} images, process 0 "
                              f"{first[0]}: every process must see the same images (the same folder, readable on "
                              "every machine)")
    if any(theirs[1] != first[1] for theirs in everyone[1:]):
        # every process sees the mismatch: all take part in this second exchange, of each image's facts
        lists = shards.gather([image_facts(p) for p in paths])
        for rank, theirs in enumerate(lists[1:], start=1):
            at = next((i for i, (a, b) in enumerate(zip(lists[0], theirs)) if a != b), None)
            if at is not None:
                raise ConfigError(f"process {rank} of {shards.world_size} lists other images than process 0: image "
                                  f"{at} is {describe_facts(theirs[at])} there, {describe_facts(lists[0][at])} in "
                                  "process 0; every process must see the same files (the same absolute paths, "
                                  "sizes and modification times)")
    for rank, theirs in enumerate(everyone[1:], start=1):
        if theirs[2:] != first[2:]:
            raise ConfigError(f"process {rank} of {shards.world_size} holds another {descriptor.name} model than "
                              f"process 0 (fingerprint {theirs[2][:12]} vs {first[2][:12]}): every machine must "
                              "load the same weights and files")


def share_fitted(shards: Shards, descriptor, paths: Sequence, fit: Callable) -> T:
    """``fit(descriptor, paths)`` (what it learnt from, or None when it learnt nothing) run on rank
    0 alone; when it learnt, the descriptor's attributes it set (no torch modules or tensors) are
    broadcast to every process. Then :func:`check_same_inputs`. Returns ``fit``'s result."""
    if not shards.enabled:
        return fit(descriptor, paths)
    before = dict(vars(descriptor))
    fitted = shards.collectively(lambda: fit(descriptor, paths), main_only=True)
    if fitted is not None:
        learnt = None
        if shards.is_main:
            learnt = {k: v for k, v in vars(descriptor).items()
                      if (k not in before or before[k] is not v) and not _holds_torch(v)}
        learnt = shards.broadcast(learnt)
        if not shards.is_main:
            vars(descriptor).update(learnt)
    check_same_inputs(shards, paths, descriptor)
    return fitted


def _holds_torch(value) -> bool:
    import sys

    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, (torch.nn.Module, torch.Tensor))


def _batches(start: int, end: int, batch_size: int) -> int:
    return -(-(end - start) // batch_size)


def _as_arrays(out) -> tuple:
    out = out if isinstance(out, (tuple, list)) else (out,)
    return tuple(np.asarray(a, dtype=np.float32) for a in out)


def kill_after(rank: int, environ: Mapping[str, str] | None = None) -> int | None:
    """The test hook (module docstring): after how many batches process ``rank`` kills itself,
    or None."""
    text = (os.environ if environ is None else environ).get(KILL_VARIABLE)
    if not text:
        return None
    who, _, batches = text.partition(":")
    try:
        who, batches = int(who), int(batches)
    except ValueError:
        raise ConfigError(f"{KILL_VARIABLE}={text!r}: expected RANK:BATCHES (a test hook)") from None
    return batches if who == rank else None


def _spool_folder() -> Path:
    import tempfile

    from fdnet.io import private_folder

    user = os.getuid() if hasattr(os, "getuid") else "user"
    # a predictable name in a shared folder: this user's alone, never a link someone else made
    return private_folder(Path(tempfile.gettempdir()) / f"fdnet-shards-{user}", "spool folder of torchrun processes")


def describe_blocks(shards: Shards, descriptor, paths: Sequence, dims: Sequence[int],
                    write: Callable[[int, tuple], None], *, batch_size: int = 64, workers: int | None = None,
                    progress: bool = True, what: str | None = None, describe=None, reads_pixels=None,
                    check: Callable[[int, tuple], None] | None = None, timing: dict | None = None) -> None:
    """Describe ``paths`` (:func:`fdnet.descriptors.pipeline.describe_stream`), this process its
    :meth:`Shards.block`, and call ``write(start, arrays)`` on rank 0 for every batch of the whole
    list, in order (``start`` indexes ``paths``; ``arrays`` one float32 (n, dim) array per entry
    of ``dims``: ``describe``'s tuple, or the descriptor's vectors). ``check(start, arrays)`` runs
    where each batch is described (e.g. refusing non-finite vectors). A single process does what
    the loop over ``describe_stream`` always did."""
    from fdnet.descriptors.pipeline import describe_stream

    paths = list(paths)
    start, end = shards.block(len(paths))
    stream = describe_stream(descriptor, paths[start:end], batch_size, workers=workers,
                             progress=progress and shards.is_main, timing=timing, describe=describe, what=what,
                             reads_pixels=reads_pixels)
    kill = kill_after(shards.rank)
    if not shards.enabled:
        for done, (first, out) in enumerate(stream, start=1):
            arrays = _as_arrays(out)
            if check is not None:
                check(first, arrays)
            write(first, arrays)
            _kill_if(kill, done)
        return
    spools: list = []
    try:
        _describe_in_lockstep(shards, stream, paths, dims, write, spools, batch_size, check, kill)
        _send_to_main(shards, spools, dims, len(paths), write)
    finally:
        stream.close()
        for spool in spools:
            spool.close()


def _kill_if(kill: int | None, done: int) -> None:
    if kill is not None and done >= kill:
        log.warning("%s: killing this process after %d batch(es) (test hook)", KILL_VARIABLE, done)
        os.kill(os.getpid(), signal.SIGKILL)


def _describe_in_lockstep(shards, stream, paths, dims, write, spools, batch_size, check, kill) -> None:
    """Rank 0 writes its batches, the others spool theirs; every process agrees on errors after
    each batch, as many times as the process with the most batches has batches."""
    from fdnet.descriptors.pipeline import VectorSpool

    start, end = shards.block(len(paths))
    steps = max(_batches(*shards.block(len(paths), r), batch_size) for r in range(shards.world_size))
    mine = _batches(start, end, batch_size)
    error = None
    if not shards.is_main:
        try:
            spools.extend(VectorSpool(_spool_folder(), dim) for dim in dims)
        except Exception as exc:  # noqa: BLE001 - agreed on below
            error = exc
    for step in range(steps):
        if error is None and step < mine:
            try:
                first, out = next(stream)
                arrays = _as_arrays(out)
                if check is not None:
                    check(start + first, arrays)
                if shards.is_main:
                    write(start + first, arrays)
                else:
                    for spool, array in zip(spools, arrays):
                        spool.write(array)
                _kill_if(kill, step + 1)
            except Exception as exc:  # noqa: BLE001 - agreed on below
                error = exc
        shards.stop_if_failed(error)
    shards.stop_if_failed(error)  # a spool that could not be made, with no batch at all
    with contextlib.suppress(StopIteration):
        next(stream)  # ends the stream: its timing is recorded


def _send_to_main(shards, spools, dims, count: int, write) -> None:
    """Every other process's spooled vectors to rank 0, block after block in rank order, in
    chunks of about CHUNK_BYTES; every process agrees on errors before each chunk and at the end."""
    import torch
    import torch.distributed as dist

    width = int(sum(dims))
    rows = max(1, CHUNK_BYTES // (4 * max(width, 1)))
    splits = np.cumsum(dims)[:-1]
    readers = [spool.chunks(rows) for spool in spools]
    error = None
    for sender in range(1, shards.world_size):
        start, end = shards.block(count, sender)
        for first in range(start, end, rows):
            n = min(rows, end - first)
            chunk = None
            if shards.rank == sender and error is None:
                try:
                    chunk = torch.from_numpy(np.ascontiguousarray(
                        np.concatenate([next(reader)[1] for reader in readers], axis=1), dtype=np.float32))
                except Exception as exc:  # noqa: BLE001 - agreed on below
                    error = exc
            shards.stop_if_failed(error)
            if shards.rank == sender:
                shards._call("sending vectors to process 0", lambda: dist.send(chunk, dst=0))
            elif shards.is_main:
                chunk = torch.empty((n, width), dtype=torch.float32)
                shards._call(f"receiving vectors from process {sender}", lambda: dist.recv(chunk, src=sender))
                try:
                    write(first, tuple(np.split(chunk.numpy(), splits, axis=1)))
                except Exception as exc:  # noqa: BLE001 - agreed on at the next chunk or below
                    error = exc
    shards.stop_if_failed(error)
