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

**Lockstep.** Every collective is entered by every rank in the same order (the one process group,
:class:`fdnet.torchrun.ProcessGroup`). Failures that only one rank sees (a held lock, a bad
setting, a full disk at a save) are agreed on with ``collectively``, so all ranks stop together
with the first rank's message instead of waiting for ever in a collective; stop decisions
(Ctrl-C, SIGTERM from torchrun, the time budget) are agreed every step with ``agree``.

**Backends.** ``gloo`` for CPU tensors, ``NCCL`` for CUDA tensors: on a machine with GPUs the
process group is ``cpu:gloo,cuda:nccl`` and each collective takes the backend of its tensors'
device (gradients of a model on a GPU go through NCCL; the small CPU objects and flags of the
lockstep through gloo); without GPUs it is ``gloo``. A process that trains on CUDA uses
``cuda:LOCAL_RANK``.

A single process (no ``WORLD_SIZE`` in the environment, or ``WORLD_SIZE=1``) gets a context on
which every method is a no-op: a plain ``fdnet train`` enters no collective.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence, TypeVar

import torch

from fdnet.errors import ConfigError
from fdnet.torchrun import ProcessGroup

T = TypeVar("T")


class DistributedContext(ProcessGroup):
    """This process's place in a data-parallel training: the one
    :class:`~fdnet.torchrun.ProcessGroup` (CUDA tensors through NCCL on a machine with GPUs, CPU
    objects through gloo) with what training adds, gradient averaging and module broadcasts (see
    the module docstring). Until :meth:`init` (and always for a single process) every collective
    returns at once with this process's own value."""

    WORK = "trains"
    START = "start distributed training"
    CPU_HINT = "runtime.device=cpu"
    USES_NCCL = True

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

        buffers = [
            b
            for module in modules
            for m in module.modules()
            if isinstance(m, _NormBase) and m.track_running_stats
            for b in m.buffers(recurse=False)
        ]
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


_SINGLE = DistributedContext()
_current: DistributedContext = _SINGLE


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

    if dist.is_available() and dist.is_initialized() and context.world_size != dist.get_world_size():
        # the caller's own process group, started without torchrun's variables: it is the group
        context = DistributedContext(dist.get_world_size(), dist.get_rank(), context.local_rank, launched=True)
    context.init()  # a group the caller started is used, and left to the caller to destroy
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
