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
:class:`~fdnet.torchrun.OtherProcessFailed` naming it, at the same step: one line each, never a hang. A process that
dies (``kill -9``) closes its connections: the others' next collective fails with
:class:`~fdnet.torchrun.LostContact`, as does torchrun's SIGTERM, so ``with`` blocks run and rank 0 removes its
parts (a killed rank 0's, or another's spool, is removed by the next run there, as for one
process). Collectives time out after :data:`fdnet.torchrun.TIMEOUT`.

**Learning from images.** A method that learns from the images it describes (``needs_fit``:
dbow without a vocabulary, trunk-whitened without ``--fit``) learns on rank 0 from all of them;
the attributes ``fit`` set are broadcast, and the fingerprint check confirms one model.

**Test hook.** ``FDNET_TEST_KILL_RANK=RANK:BATCHES`` (read only here): process RANK SIGKILLs itself
after BATCHES batches, how the tests kill one mid-run. Never set it otherwise.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Mapping, Sequence, TypeVar

import numpy as np

from fdnet.errors import ConfigError
from fdnet.torchrun import LostContact, OtherProcessFailed, ProcessGroup  # noqa: F401  (raised in every process)

log = logging.getLogger(__name__)

T = TypeVar("T")

#: bytes of vectors sent to rank 0 at a time
CHUNK_BYTES = 16 << 20
#: the test hook's environment variable (module docstring)
KILL_VARIABLE = "FDNET_TEST_KILL_RANK"


class Shards(ProcessGroup):
    """The :class:`~fdnet.torchrun.ProcessGroup` of processes describing one image list (module
    docstring): gloo only (the vectors are on the CPU by then), a CPU process using the machine's
    cores divided among its processes."""

    WORK = "describes"
    CPU_HINT = "--device cpu"
    DIVIDES_CORES = True


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
def launch(environ: Mapping[str, str] | None = None) -> Iterator[Shards]:
    """Join the processes the environment describes for the block, make them :func:`current`, stop
    on SIGTERM with an error and quiet all but rank 0; one process gets a no-op context, a nested
    launch the running one. A process that joined a group leaves by ``os._exit`` once its exit
    handlers ran (:func:`fdnet.torchrun.exit_process`, which ``fdnet``'s command line calls)."""
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
    try:
        with shards.quiet_unless_main():
            yield shards
    finally:
        restore()
        _current = _SINGLE
        shards.destroy()


def _stop_on_sigterm() -> Callable[[], None]:
    """SIGTERM (torchrun stopping every process, one having failed) raises LostContact here, so
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
        raise LostContact(
            "stopped by SIGTERM: torchrun stops every process when one of them fails or is "
            "killed (its error, if any, is above)"
        )

    previous = signal.signal(signal.SIGTERM, stop)
    return lambda: signal.signal(signal.SIGTERM, previous)


# ---------------------------------------------------------------------- the work
def check_same_inputs(shards: Shards, paths: Sequence, descriptor) -> None:
    """ConfigError in every process unless all of them list the same images (by content:
    :func:`fdnet.data.identity.images_digest`, each image's absolute path, size and modification
    time, in order) and hold the same model (its fingerprint). Two folders whose images share
    file names are two image lists."""
    if not shards.enabled:
        return
    from fdnet.data.identity import describe_facts, image_facts, images_digest

    mine = shards.collectively(
        lambda: (len(paths), images_digest(paths), descriptor.fingerprint(), int(descriptor.dim))
    )
    everyone = shards.gather(mine)
    first = everyone[0]
    for rank, theirs in enumerate(everyone[1:], start=1):
        if theirs[0] != first[0]:
            raise ConfigError(
                f"process {rank} of {shards.world_size} lists {theirs[0]} images, process 0 "
                f"{first[0]}: every process must see the same images (the same folder, readable on "
                "every machine)"
            )
    if any(theirs[1] != first[1] for theirs in everyone[1:]):
        # every process sees the mismatch: all take part in this second exchange, of each image's facts
        lists = shards.gather([image_facts(p) for p in paths])
        for rank, theirs in enumerate(lists[1:], start=1):
            at = next((i for i, (a, b) in enumerate(zip(lists[0], theirs)) if a != b), None)
            if at is not None:
                raise ConfigError(
                    f"process {rank} of {shards.world_size} lists other images than process 0: image "
                    f"{at} is {describe_facts(theirs[at])} there, {describe_facts(lists[0][at])} in "
                    "process 0; every process must see the same files (the same absolute paths, "
                    "sizes and modification times)"
                )
    for rank, theirs in enumerate(everyone[1:], start=1):
        if theirs[2:] != first[2:]:
            raise ConfigError(
                f"process {rank} of {shards.world_size} holds another {descriptor.name} model than "
                f"process 0 (fingerprint {theirs[2][:12]} vs {first[2][:12]}): every machine must "
                "load the same weights and files"
            )


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
            learnt = {
                k: v
                for k, v in vars(descriptor).items()
                if (k not in before or before[k] is not v) and not _holds_torch(v)
            }
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
    except ValueError as exc:
        raise ConfigError(f"{KILL_VARIABLE}={text!r}: expected RANK:BATCHES (a test hook)") from exc
    return batches if who == rank else None


def _spool_folder() -> Path:
    import tempfile

    from fdnet.io import private_folder

    user = os.getuid() if hasattr(os, "getuid") else "user"
    # a predictable name in a shared folder: this user's alone, never a link someone else made
    return private_folder(Path(tempfile.gettempdir()) / f"fdnet-shards-{user}", "spool folder of torchrun processes")


@dataclass(frozen=True)
class BlockOutput:
    """Where :func:`describe_blocks` puts what it describes: ``write(start, arrays)`` on rank 0
    for every batch of the whole list, in order (``start`` indexes the paths; ``arrays`` one
    float32 (n, dim) array per entry of ``dims``: the job's ``describe`` tuple, or the
    descriptor's vectors); ``check(start, arrays)`` where each batch is described (e.g. refusing
    non-finite vectors)."""

    dims: Sequence[int]
    write: Callable[[int, tuple], None]
    check: Callable[[int, tuple], None] | None = None


def describe_blocks(
    shards: Shards,
    descriptor,
    paths: Sequence,
    output: BlockOutput,
    pipeline=None,
    job=None,
    timing: dict | None = None,
) -> None:
    """Describe ``paths`` (:func:`fdnet.descriptors.pipeline.describe_stream` with ``pipeline``,
    default batches of 64 with a progress bar, and ``job``), this process its
    :meth:`Shards.block`, and hand every batch of the whole list to ``output`` on rank 0, in
    order. A single process does what a loop over ``describe_stream`` does."""
    from fdnet.descriptors.pipeline import PipelineSettings, describe_stream

    pipeline = pipeline or PipelineSettings(batch_size=64, progress=True)
    batch_size, write, check = pipeline.batch_size, output.write, output.check
    paths = list(paths)
    start, end = shards.block(len(paths))
    stream = describe_stream(
        descriptor,
        paths[start:end],
        PipelineSettings(batch_size, pipeline.workers, pipeline.progress and shards.is_main),
        job,
        timing,
    )
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
        _describe_in_lockstep(shards, stream, paths, output, spools, batch_size, kill)
        _send_to_main(shards, spools, output.dims, len(paths), write)
    finally:
        stream.close()
        for spool in spools:
            spool.close()


def _kill_if(kill: int | None, done: int) -> None:
    if kill is not None and done >= kill:
        log.warning("%s: killing this process after %d batch(es) (test hook)", KILL_VARIABLE, done)
        os.kill(os.getpid(), signal.SIGKILL)


def _describe_in_lockstep(shards, stream, paths, output: BlockOutput, spools, batch_size, kill) -> None:
    """Rank 0 writes its batches, the others spool theirs; every process agrees on errors after
    each batch, as many times as the process with the most batches has batches."""
    from fdnet.descriptors.pipeline import VectorSpool

    dims, write, check = output.dims, output.write, output.check
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
                    chunk = torch.from_numpy(
                        np.ascontiguousarray(
                            np.concatenate([next(reader)[1] for reader in readers], axis=1), dtype=np.float32
                        )
                    )
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
