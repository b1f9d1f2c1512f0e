"""Data-parallel training over ``torch.distributed``, started by ``torchrun``.

``torchrun --nproc-per-node N [--nnodes M --node-rank K --rdzv-endpoint HOST:PORT] -m fdnet train ...``
starts one process per GPU (or N CPU processes); each reads ``WORLD_SIZE``, ``RANK`` and
``LOCAL_RANK`` from its environment (:meth:`DistributedContext.from_env`). Every process holds the
whole model and the whole training set and draws its own domain-balanced batches; before every
optimiser step the gradients are averaged over the processes, so all of them apply the same update
and keep identical weights (the effective batch is ``world_size`` x the per-process batch).

**Why not DistributedDataParallel.** FDNet's critic is trained with the WGAN-GP gradient penalty, a
double backward (``torch.autograd.grad(..., create_graph=True)``, see
:func:`fdnet.methods.fdnet.losses.critic_loss`). DDP does not support double backward: its reducer
synchronises the gradients of the first backward only, and gradients of gradients are not
averaged (pytorch/pytorch#63929, #47562). So no module is wrapped in DDP; after ``backward()``
each method calls :meth:`DistributedContext.average_gradients` on the optimiser it is about to
step, which flattens that optimiser's gradients into one bucket per device and dtype, all-reduces
it and copies the averages back: what DDP's reducer does for an ordinary backward, here after the
whole (double) backward is done. It does not overlap communication with the backward pass.

**Who does what.** Rank 0 alone holds the run directory's lock, checks a fresh run's or a resume's
preconditions, reads the run on ``--resume`` (weights, optimiser and training state, then
broadcast to the others, so the other processes need no access to the run directory, e.g. on
machines without a shared filesystem), validates, writes ``best/``, ``log.csv`` and every
checkpoint. Before each checkpoint every rank's own random state (its sampler generator and
torch's RNG) is gathered to rank 0 and saved, so a resume with the same world size continues each
rank's random streams exactly. The other ranks only compute and take part in the collectives.

**Lockstep.** Every collective is entered by every rank in the same order. Failures that only one
rank sees (a held lock, a bad setting, a full disk at a save) are agreed on with
:meth:`collectively`, so all ranks stop together with the first rank's message instead of
waiting for ever in a collective; stop decisions (Ctrl-C, SIGTERM from torchrun, the time budget)
are agreed every step with :meth:`agree`.

**Backends.** ``gloo`` for CPU tensors, ``NCCL`` for CUDA tensors: on a machine with GPUs the
process group is ``cpu:gloo,cuda:nccl`` and each collective takes the backend of its tensors'
device (gradients of a model on a GPU go through NCCL; the small CPU objects and flags of the
lockstep through gloo); without GPUs it is ``gloo``. A process that trains on CUDA uses
``cuda:LOCAL_RANK``.

A single process (no ``WORLD_SIZE`` in the environment, or ``WORLD_SIZE=1``) gets a context on
which every method is a no-op, so a plain ``fdnet train`` behaves as it always did.
"""

from __future__ import annotations

import contextlib
import datetime
import os
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence, TypeVar

import torch

from fdnet.errors import ConfigError, FdnetError
from fdnet.torchrun import environment_int, leave, quiet_unless, require_rendezvous

T = TypeVar("T")

#: How long a collective may wait for the slowest rank. Rank 0 validates alone while the others
#: wait in the next step's collective, so a validation must take less than this.
TIMEOUT = datetime.timedelta(minutes=30)


#: how a training's processes are started, named when torchrun's variables are missing
_START = "start distributed training"


class OtherRankFailed(FdnetError):
    """Raised on the ranks that did not fail themselves when another rank failed (see
    :meth:`DistributedContext.collectively`)."""


class DistributedContext:
    """This process's place in a data-parallel training (see the module docstring).

    ``world_size`` processes in all, this one is ``rank`` (0 = the one that writes) and
    ``local_rank`` on its machine. :attr:`enabled` once a process group with more than one
    process is initialised; until then (and always for a single process) every collective below
    returns at once with this process's own value.
    """

    def __init__(self, world_size: int = 1, rank: int = 0, local_rank: int = 0, launched: bool = False) -> None:
        if world_size < 1 or not 0 <= rank < world_size or local_rank < 0:
            raise ConfigError(f"invalid distributed setup: RANK={rank}, LOCAL_RANK={local_rank}, "
                              f"WORLD_SIZE={world_size} (need 0 <= RANK < WORLD_SIZE)")
        self.world_size = int(world_size)
        self.rank = int(rank)
        self.local_rank = int(local_rank)
        #: started by torchrun (or another launcher that sets WORLD_SIZE)
        self.launched = bool(launched)
        self.enabled = False
        self.backend: str | None = None

    def __repr__(self) -> str:
        return (f"DistributedContext(world_size={self.world_size}, rank={self.rank}, "
                f"local_rank={self.local_rank}, backend={self.backend})")

    # ------------------------------------------------------------------ set-up
    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "DistributedContext":
        """``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK`` as torchrun sets them; a single process when
        ``WORLD_SIZE`` is absent."""
        environ = os.environ if environ is None else environ
        if "WORLD_SIZE" not in environ:
            return cls()
        world_size = environment_int(environ, "WORLD_SIZE", start=_START)
        rank = environment_int(environ, "RANK", start=_START)
        local_rank = environment_int(environ, "LOCAL_RANK", default=0)
        return cls(world_size, rank, local_rank, launched=True)

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that holds the lock and writes the run directory."""
        return self.rank == 0

    def init(self) -> "DistributedContext":
        """Join the process group (a no-op for one process). On a machine with GPUs, this process's
        current CUDA device becomes ``cuda:LOCAL_RANK`` first, so ``cuda``/``auto`` mean that GPU."""
        if torch.cuda.is_available() and self.local_rank < torch.cuda.device_count():
            torch.cuda.set_device(self.local_rank)
        if self.world_size == 1 or self.enabled:
            return self
        import torch.distributed as dist

        if not dist.is_available() or not dist.is_gloo_available():
            raise ConfigError("this torch build has no torch.distributed with gloo; distributed training needs it")
        require_rendezvous(os.environ, self.world_size, start=_START)
        backend = "cpu:gloo,cuda:nccl" if torch.cuda.is_available() and dist.is_nccl_available() else "gloo"
        dist.init_process_group(backend, init_method="env://", world_size=self.world_size, rank=self.rank,
                                timeout=TIMEOUT)
        global _joined_a_group
        _joined_a_group = True
        self.backend = backend
        self.enabled = True
        return self

    def destroy(self) -> None:
        if self.enabled:
            import torch.distributed as dist

            dist.destroy_process_group()
            self.enabled = False
            self.backend = None

    def check_device(self, device: torch.device | None) -> None:
        """ConfigError unless a CUDA ``device`` is this process's own GPU, ``cuda:LOCAL_RANK``
        (two processes on one GPU would slow each other down and NCCL refuses them)."""
        if device is None or not self.launched or self.world_size == 1:
            return
        device = torch.device(device)
        if device.type != "cuda":
            return
        count = torch.cuda.device_count()
        index = device.index if device.index is not None else torch.cuda.current_device()
        if self.local_rank >= count:
            raise ConfigError(
                f"process {self.rank} (LOCAL_RANK {self.local_rank}) has no GPU of its own: this machine has "
                f"{count} GPU(s) and each process trains on cuda:LOCAL_RANK; start at most {count} processes "
                f"per machine (torchrun --nproc-per-node {count}) or train on CPUs (runtime.device=cpu)")
        if index != self.local_rank:
            raise ConfigError(
                f"device {device} for process {self.rank}: with torchrun each process trains on its own GPU, "
                f"cuda:LOCAL_RANK (here cuda:{self.local_rank}); set the device to cuda or auto, not cuda:N")

    def rank_seed(self, seed: int) -> int:
        """The seed of this rank's data streams: ``seed + rank``. Rank 0 keeps ``seed``, so a
        single process draws what it always drew; rank r draws other batches than rank 0."""
        return int(seed) + self.rank

    # ------------------------------------------------------------------ collectives
    def average_gradients(self, optimizer: torch.optim.Optimizer, loss: torch.Tensor | None = None) -> bool:
        """Replace the gradients of ``optimizer``'s parameters by their mean over all ranks; call it
        after ``backward()`` and before ``optimizer.step()``.

        With ``loss``, returns whether that loss is finite on every rank (a flag rides along in the
        gradient bucket, so this costs no extra collective); a method then raises on every rank at
        the same step instead of one rank stopping while the others wait. Parameters without a
        gradient are left alone: every rank runs the same code, so the same parameters have one.
        """
        nonfinite = None if loss is None else ~torch.isfinite(loss.detach()).reshape(1)
        if not self.enabled:
            return nonfinite is None or not bool(nonfinite)
        import torch.distributed as dist
        from torch._utils import _flatten_dense_tensors, _unflatten_dense_tensors

        grads = [p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        buckets: dict[tuple[torch.device, torch.dtype], list[torch.Tensor]] = {}
        for grad in grads:
            if grad.is_sparse:
                raise ConfigError("distributed training averages dense gradients only (a sparse one was found)")
            buckets.setdefault((grad.device, grad.dtype), []).append(grad)
        any_nonfinite = False
        for (device, dtype), tensors in buckets.items():
            flat = _flatten_dense_tensors(tensors)
            if nonfinite is not None and dtype.is_floating_point:
                # the flag as one more element of the first floating-point bucket: summed over ranks
                flat = torch.cat([flat, nonfinite.to(device=device, dtype=dtype)])
                dist.all_reduce(flat)
                any_nonfinite = bool(flat[-1] > 0)
                flat, nonfinite = flat[:-1], None
            else:
                dist.all_reduce(flat)
            flat.div_(self.world_size)
            for grad, mean in zip(tensors, _unflatten_dense_tensors(flat, tensors)):
                grad.copy_(mean)
        if nonfinite is not None:  # no floating-point gradient carried the flag
            any_nonfinite = self.agree(bool(nonfinite))[0]
        return loss is None or not any_nonfinite

    def broadcast_module(self, module: torch.nn.Module) -> None:
        """Overwrite ``module``'s parameters and buffers with rank 0's (one bucket per device and
        dtype)."""
        if self.enabled:
            self._broadcast([*module.parameters(), *module.buffers()])

    def broadcast_buffers(self, modules: Iterable[torch.nn.Module]) -> None:
        """Overwrite the running statistics of the normalisation layers in ``modules`` with rank
        0's, as DistributedDataParallel does before each forward (``broadcast_buffers=True``): each
        rank updates them from its own batches, so without this they would drift apart. Other
        buffers (a fitted mean, NetVLAD's PCA) do not change in a training step and are left
        alone (a PCA projection can be hundreds of MB)."""
        if not self.enabled:
            return
        from torch.nn.modules.batchnorm import _NormBase

        buffers = [b for module in modules for m in module.modules()
                   if isinstance(m, _NormBase) and m.track_running_stats for b in m.buffers(recurse=False)]
        if buffers:
            self._broadcast(buffers)

    def _broadcast(self, tensors: list[torch.Tensor]) -> None:
        import torch.distributed as dist
        from torch._utils import _flatten_dense_tensors, _unflatten_dense_tensors

        buckets: dict[tuple[torch.device, torch.dtype], list[torch.Tensor]] = {}
        for tensor in tensors:
            buckets.setdefault((tensor.device, tensor.dtype), []).append(tensor)
        with torch.no_grad():
            for group in buckets.values():
                flat = _flatten_dense_tensors([t.detach() for t in group])
                dist.broadcast(flat, src=0)
                for tensor, value in zip(group, _unflatten_dense_tensors(flat, group)):
                    tensor.copy_(value)

    def broadcast_object(self, obj: T) -> T:
        """Rank 0's ``obj`` on every rank (pickled; CPU tensors inside it stay CPU tensors)."""
        if not self.enabled:
            return obj
        import torch.distributed as dist

        box = [obj if self.is_main else None]
        dist.broadcast_object_list(box, src=0)
        return box[0]

    def gather_objects(self, obj: Any) -> list | None:
        """Every rank's ``obj``, in rank order, on rank 0 (None on the other ranks)."""
        if not self.enabled:
            return [obj]
        import torch.distributed as dist

        out = [None] * self.world_size if self.is_main else None
        dist.gather_object(obj, out, dst=0)
        return out

    def agree(self, *flags: bool) -> tuple[bool, ...]:
        """Each flag true on any rank, on every rank (one small all-reduce): stop decisions that
        every rank must take at the same step."""
        if not self.enabled:
            return tuple(bool(f) for f in flags)
        import torch.distributed as dist

        tensor = torch.tensor([1 if f else 0 for f in flags], dtype=torch.int32)  # CPU: gloo
        dist.all_reduce(tensor, op=dist.ReduceOp.MAX)
        return tuple(bool(v) for v in tensor.tolist())

    def collectively(self, fn: Callable[[], T], main_only: bool = False) -> T:
        """Run ``fn`` on every rank (or on rank 0 alone, with ``main_only``, whose result is then
        broadcast) and agree on failure: when ``fn`` raised on any rank, every rank raises, the
        failing ones their own exception and the others :class:`OtherRankFailed` with the first
        failure's message. ``fn`` must not itself enter a collective."""
        if not self.enabled:
            return fn()
        result, error = None, None
        if not main_only or self.is_main:
            try:
                result = fn()
            except Exception as exc:  # noqa: BLE001 - re-raised below, on every rank
                error = exc
        import torch.distributed as dist

        failures: list = [None] * self.world_size
        dist.all_gather_object(failures, None if error is None else
                               (str(error) if isinstance(error, FdnetError) else f"{type(error).__name__}: {error}"))
        if error is not None:
            raise error
        for rank, failure in enumerate(failures):
            if failure is not None:
                raise OtherRankFailed(f"stopped because process {rank} of {self.world_size} failed: {failure}")
        return self.broadcast_object(result) if main_only else result

    # ------------------------------------------------------------------ output
    def quiet_unless_main(self):
        """One process reports (:func:`fdnet.torchrun.quiet_unless`)."""
        return quiet_unless(self.is_main)


_SINGLE = DistributedContext()
_current: DistributedContext = _SINGLE
#: whether this process ever joined a process group (see :func:`exit_process`)
_joined_a_group = False


def exit_process(code: int) -> None:
    """End this process with ``code``: :func:`sys.exit`, except in a process that joined a
    process group, which leaves by :func:`fdnet.torchrun.leave` (exit handlers, flushed output,
    ``os._exit``: gloo's native teardown at interpreter exit now and then aborts a finished run).
    """
    import sys

    if not _joined_a_group:
        sys.exit(code)
    leave(code)


def current() -> DistributedContext:
    """The context of this process's running training (a single-process no-op one outside
    :func:`launch`)."""
    return _current


@contextlib.contextmanager
def launch(environ: Mapping[str, str] | None = None) -> Iterator[DistributedContext]:
    """Join the process group the environment describes (torchrun's variables) for the duration
    of the block and make it :func:`current`; a single process gets the no-op context. Nested
    calls reuse the running context (the CLI launches, then ``run_training`` finds it)."""
    global _current
    if _current is not _SINGLE:
        yield _current
        return
    context = DistributedContext.from_env(environ)
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        # the caller's own process group: use it, and leave it to the caller to destroy
        context = DistributedContext(dist.get_world_size(), dist.get_rank(), context.local_rank, launched=True)
        context.enabled = context.world_size > 1
        context.backend = str(dist.get_backend())
        _current = context
        try:
            yield context
        finally:
            _current = _SINGLE
        return
    context.init()
    _current = context
    try:
        yield context
    finally:
        _current = _SINGLE
        context.destroy()


def run_with_settings_from_rank_0(build: Callable[[], Any], work: Callable[[Any], T]) -> T:
    """``work(settings)`` in every process of a torchrun launch (or in the one process of a plain
    command), ``settings = build()`` computed by rank 0 alone and broadcast (it alone reads
    ``--config`` files and, on ``--resume``, the run's own settings); only rank 0 prints."""
    with launch() as context:
        settings = context.collectively(build, main_only=True)
        with context.quiet_unless_main():
            return work(settings)


def rank_part(state: dict, keys: Sequence[str] | None) -> dict:
    """The entries of a method state that are this rank's own (``keys``; all when None)."""
    return dict(state) if keys is None else {k: state[k] for k in keys if k in state}


def merge_rank_state(shared: dict, own: dict, keys: Sequence[str] | None) -> dict:
    """One rank's method state: rank 0's saved state (what the ranks share) with the rank's own
    entries (``keys``; all of them when None) taken from ``own``."""
    return {**(shared if keys is not None else {}), **rank_part(own, keys)}


def loss_text(loss: torch.Tensor) -> str:
    """How to report a loss that :meth:`DistributedContext.average_gradients` found non-finite:
    its value where it is so, else that it was so in another process."""
    value = float(loss.detach())
    return f"{value}" if not torch.isfinite(torch.tensor(value)) else "non-finite in another training process"
