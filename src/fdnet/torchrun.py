"""The one process group of a torchrun launch, whether it trains (:mod:`fdnet.training.distributed`
adds gradient averaging to it) or describes a map (:mod:`fdnet.descriptors.sharding`):
:class:`ProcessGroup` (its place read from the environment, the process group joined and left, the
collectives every process enters in the same order, failures agreed on so that no process waits
for ever), one process reporting, and an exit that skips gloo's native teardown
(:func:`exit_process`). torch is imported only inside the methods that need it, so inference code
uses this without reaching training code.

**Lockstep.** Every collective is entered by every process in the same order. Failures that only
one process sees (a held lock, a bad setting, an unreadable image, a full disk) are agreed on with
:meth:`ProcessGroup.collectively` / :meth:`ProcessGroup.stop_if_failed`: the failing processes
raise their own error, the others :class:`OtherProcessFailed` naming the first, at the same step.
A lost process (killed, or stopped by torchrun) turns the others' next collective into a
:class:`LostContact` error of one line. Collectives time out after :data:`TIMEOUT`."""

from __future__ import annotations

import contextlib
import datetime
import logging
import os
from typing import Callable, Iterator, Mapping, TypeVar

from fdnet.errors import ConfigError, FdnetError

T = TypeVar("T")

#: how long a collective waits for the slowest process (the longest waits: rank 0 validating a
#: training, or fitting a method on every image, while the others wait in the next collective)
TIMEOUT = datetime.timedelta(minutes=30)
#: whether this process ever joined a process group of its own (see :func:`exit_process`)
_joined_a_group = False


class LostContact(FdnetError):
    """The processes lost contact (one died, or torchrun stopped them), or the launch is unusable."""


class OtherProcessFailed(FdnetError):
    """Raised on the processes that did not fail themselves when another one failed."""


def environment_int(
    environ: Mapping[str, str], name: str, default: int | None = None, start: str = "start several processes"
) -> int:
    """The integer torchrun put in ``name``; ``default`` when it is absent (None: absent is an
    error saying how to ``start`` the processes)."""
    text = environ.get(name)
    if text is None:
        if default is None:
            raise ConfigError(
                f"WORLD_SIZE is set but {name} is not: {start} with torchrun "
                "(it sets WORLD_SIZE, RANK, LOCAL_RANK, MASTER_ADDR and MASTER_PORT)"
            )
        return default
    try:
        return int(text)
    except ValueError as exc:
        raise ConfigError(f"environment variable {name}={text!r} is not an integer") from exc


def require_rendezvous(environ: Mapping[str, str], world_size: int, start: str = "start several processes") -> None:
    """ConfigError unless torchrun's rendezvous address is set (``env://`` needs both)."""
    missing = [name for name in ("MASTER_ADDR", "MASTER_PORT") if name not in environ]
    if missing:
        raise ConfigError(f"WORLD_SIZE={world_size} is set but {' and '.join(missing)} not: {start} with torchrun")


@contextlib.contextmanager
def quiet_unless(is_main: bool) -> Iterator[None]:
    """Standard output and the messages below WARNING (:mod:`fdnet.logs`) of the processes other
    than rank 0 go nowhere (their warnings and errors still reach standard error): one process
    reports, not N copies of it."""
    if is_main:
        yield
        return
    logger = logging.getLogger("fdnet")
    level = logger.level
    logger.setLevel(max(level, logging.WARNING))
    try:
        with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
            yield
    finally:
        logger.setLevel(level)


def leave(code: int) -> None:
    """Run the ``atexit`` handlers, flush the output and end by :func:`os._exit`.

    Why: after ``destroy_process_group`` a gloo process still holds native threads that C++ tears
    down at interpreter exit; now and then (a few runs in a hundred, more under load) one is still
    joinable then and the process dies of ``std::terminate`` (SIGABRT) after its work had finished
    and been saved, so torchrun reports a failure. Skipping the native teardown avoids it; nothing
    of ours is left to it."""
    import atexit
    import sys

    atexit._run_exitfuncs()  # what a normal exit would still run (logging handlers, temp files)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def exit_process(code: int) -> None:
    """End this process with ``code``: :func:`sys.exit`, except in a process that joined a
    process group of its own, which leaves by :func:`leave` (exit handlers, flushed output,
    ``os._exit``: gloo's native teardown at interpreter exit now and then aborts a finished run)."""
    import sys

    if not _joined_a_group:
        sys.exit(code)
    leave(code)


def _backend_message(exc: BaseException) -> str:
    """A gloo error's first sentence without its source location ("Connection closed by peer ...")."""
    import re

    text = re.sub(r"\[[^\]]*\.(cc|cpp|h):\d+\]\s*", "", " ".join(str(exc).split()))
    return (text.split(". ")[0] or type(exc).__name__)[:300]


def _one_line(exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, FdnetError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split())


class ProcessGroup:
    """This process's place among ``world_size`` processes started by torchrun (module
    docstring): ``rank`` 0 is the one that writes; ``local_rank`` is the process's index on its
    machine (its GPU), one of ``local_world_size`` there; ``launched``: torchrun's variables are
    set. Until :meth:`init` (and always for one process) every collective returns at once with
    this process's own value. Subclasses say what the processes do (:attr:`WORK`, how to
    :attr:`START` them, whether CUDA tensors go through NCCL, whether CPU cores are divided)."""

    #: what each process does on its GPU, for messages
    WORK = "works"
    #: how the processes are started, named when torchrun's variables are missing
    START = "start several processes"
    #: how to leave the GPUs, for messages
    CPU_HINT = "--device cpu"
    #: CUDA tensors through NCCL (training's gradients) besides gloo for CPU objects
    USES_NCCL = False
    #: a CPU process uses the machine's cores divided among its processes
    DIVIDES_CORES = False

    def __init__(
        self, world_size: int = 1, rank: int = 0, local_rank: int = 0, local_world_size: int = 1, launched: bool = False
    ):
        if world_size < 1 or not 0 <= rank < world_size or local_rank < 0 or local_world_size < 1:
            raise ConfigError(
                f"invalid torchrun setup: RANK={rank}, LOCAL_RANK={local_rank}, "
                f"WORLD_SIZE={world_size}, LOCAL_WORLD_SIZE={local_world_size} "
                "(need 0 <= RANK < WORLD_SIZE)"
            )
        self.world_size = int(world_size)
        self.rank = int(rank)
        self.local_rank = int(local_rank)
        self.local_world_size = int(local_world_size)
        self.launched = bool(launched)
        self.enabled = False
        self.backend: str | None = None
        self._owns_group = False

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(world_size={self.world_size}, rank={self.rank}, "
            f"local_rank={self.local_rank}, backend={self.backend})"
        )

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None):
        """torchrun's ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``; one process
        when ``WORLD_SIZE`` is absent."""
        environ = os.environ if environ is None else environ
        if "WORLD_SIZE" not in environ:
            return cls()
        return cls(
            environment_int(environ, "WORLD_SIZE", start=cls.START),
            environment_int(environ, "RANK", start=cls.START),
            environment_int(environ, "LOCAL_RANK", 0),
            environment_int(environ, "LOCAL_WORLD_SIZE", 1),
            launched=True,
        )

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes."""
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
    def init(self):
        """Join the process group (a no-op for one process), after making ``cuda:LOCAL_RANK`` this
        process's current CUDA device on a machine with GPUs, so ``cuda``/``auto`` mean that GPU.
        A process group the caller already started is used, and left to the caller to destroy."""
        import torch

        if torch.cuda.is_available() and self.local_rank < torch.cuda.device_count():
            torch.cuda.set_device(self.local_rank)
        if self.world_size == 1 or self.enabled:
            return self
        import torch.distributed as dist

        if not dist.is_available() or not dist.is_gloo_available():
            raise ConfigError("this torch build has no torch.distributed with gloo; several processes need it")
        if dist.is_initialized():
            if dist.get_world_size() != self.world_size:
                raise ConfigError(
                    f"WORLD_SIZE={self.world_size} but the running process group has "
                    f"{dist.get_world_size()} processes"
                )
            self.rank, self.backend, self.enabled = dist.get_rank(), str(dist.get_backend()), True
            return self
        require_rendezvous(os.environ, self.world_size, start=self.START)
        backend = (
            "cpu:gloo,cuda:nccl"
            if self.USES_NCCL and torch.cuda.is_available() and dist.is_nccl_available()
            else "gloo"
        )
        self._call(
            "joining the other processes",
            lambda: dist.init_process_group(
                backend, init_method="env://", world_size=self.world_size, rank=self.rank, timeout=TIMEOUT
            ),
        )
        global _joined_a_group
        _joined_a_group = True
        self.backend, self.enabled, self._owns_group = backend, True, True
        if self.DIVIDES_CORES:
            torch.set_num_threads(self.threads())
        return self

    def destroy(self) -> None:
        if self.enabled and self._owns_group:
            import torch.distributed as dist

            with contextlib.suppress(Exception):  # after a lost process it may fail too: nothing to save
                dist.destroy_process_group()
        self.enabled = self._owns_group = False
        self.backend = None

    def check_device(self, device) -> None:
        """ConfigError unless a CUDA ``device`` is this process's own GPU, ``cuda:LOCAL_RANK`` (two
        processes on one GPU would slow each other down and NCCL refuses them)."""
        if device is None or self.world_size == 1:
            return
        import torch

        device = torch.device(device)
        if device.type != "cuda":
            return
        count = torch.cuda.device_count()
        if self.local_rank >= count:
            raise ConfigError(
                f"process {self.rank} (LOCAL_RANK {self.local_rank}) has no GPU of its own: this "
                f"machine has {count} GPU(s) and each process {self.WORK} on cuda:LOCAL_RANK; start "
                f"at most {count} processes per machine (torchrun --nproc-per-node {count}) or use "
                f"{self.CPU_HINT}"
            )
        if device.index is not None and device.index != self.local_rank:
            raise ConfigError(
                f"device {device} for process {self.rank}: under torchrun each process {self.WORK} on "
                f"its own GPU, cuda:LOCAL_RANK (here cuda:{self.local_rank}); give cuda or auto, "
                "not cuda:N"
            )

    # ------------------------------------------------------------------ collectives
    def _call(self, what: str, fn: Callable[[], T]) -> T:
        """``fn()``, a torch.distributed call: a lost process becomes one line, not a traceback."""
        try:
            return fn()
        except RuntimeError as exc:  # gloo: connection closed or reset by a peer, a timeout
            raise LostContact(
                f"process {self.rank} of {self.world_size} lost contact with the others while "
                f"{what} (another process stopped or was killed; its error, if any, is above): "
                f"{_backend_message(exc)}"
            ) from exc

    def agree(self, *flags: bool) -> tuple[bool, ...]:
        """Each flag true in any process, in every process (one small all-reduce): decisions that
        every process must take at the same step."""
        if not self.enabled:
            return tuple(bool(f) for f in flags)
        import torch
        import torch.distributed as dist

        tensor = torch.tensor([1 if f else 0 for f in flags], dtype=torch.int32)  # CPU: gloo
        self._call("agreeing", lambda: dist.all_reduce(tensor, op=dist.ReduceOp.MAX))
        return tuple(bool(v) for v in tensor.tolist())

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` is true in any process."""
        return self.agree(flag)[0]

    def gather(self, obj) -> list:
        """Every process's ``obj``, in rank order, in every process."""
        if not self.enabled:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world_size
        self._call("exchanging settings", lambda: dist.all_gather_object(out, obj))
        return out

    def gather_to_main(self, obj) -> list | None:
        """Every process's ``obj``, in rank order, on rank 0 (None in the other processes)."""
        if not self.enabled:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world_size if self.is_main else None
        self._call("sending state to rank 0", lambda: dist.gather_object(obj, out, dst=0))
        return out

    def broadcast(self, obj: T) -> T:
        """Rank 0's ``obj`` in every process (pickled; CPU tensors inside it stay CPU tensors)."""
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

    def quiet_unless_main(self):
        """One process reports (:func:`quiet_unless`)."""
        return quiet_unless(self.is_main)
