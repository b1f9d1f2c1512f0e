"""The one training loop every trained method runs on (FDNet, CALC, NetVLAD).

A method contributes a :class:`TrainingMethod`: its modules, optimisers, one ``train_step`` and
the state it needs to continue exactly. :func:`run_training` does everything else, the same way
for every method:

* a lock on the run directory (a second ``train``/``--resume`` on it stops with the holder's pid);
* a fresh run refuses a folder that already holds one; ``--resume`` compares the requested
  settings with the run's and refuses any difference unless ``override`` is given, in which case
  the change and its step are recorded in ``changes.yaml``;
* crash-safe checkpoints (:mod:`fdnet.runs`: weights + training state + config published as one
  unit, the previous one kept until the new one is complete) every ``checkpoint_every`` steps,
  at the end, at the time budget and on Ctrl-C;
* exact resume: the method's own state plus torch's global RNG (dropout) are in the checkpoint;
* periodic validation (R@1 of cosine matching, ties to the higher AUC) with ``best/``;
* ``log.csv`` (rows after the resumed checkpoint are dropped) and a progress bar;
* device, precision and threads: every method's ``runtime`` section (``runtime.device``,
  ``runtime.bf16``, ``runtime.threads``) goes through :func:`training_device`,
  :func:`training_precision` and :func:`autocast`, and :func:`run_training` checks the device
  before any image is read;
* data-parallel training when started by ``torchrun`` (:mod:`fdnet.training.distributed`): rank 0
  holds the lock, reads and writes the run directory, validates and logs; every rank's random
  state is saved; the world size is recorded and a resume with another one refused unless
  ``override``; stop decisions and failures are agreed so no rank waits for ever. A method takes
  part through :attr:`TrainingMethod.distributed`: it averages its gradients before every
  optimiser step and seeds its data streams per rank.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np
import torch

from fdnet import runs
from fdnet.errors import ConfigError, output_error
from fdnet.io import atomic_write_text, ensure_writable
from fdnet.training import distributed as dist_module
from fdnet.training.data import ValidationImages
from fdnet.training.distributed import DistributedContext
from fdnet.training.logging import TrainingLog

BEST_DIR = runs.BEST_DIR
#: RUN/stages/STAGE/: the weights at the end of each training stage
STAGES_DIR = "stages"


@dataclass
class LoopSettings:
    """How long and how often: read from each method's own config section."""

    total_steps: int
    checkpoint_every: int
    log_every: int
    #: validate every N steps (0 = never, also when no validation images are given)
    validate_every: int = 0


class TrainingMethod(ABC):
    """What one trained method adds to the shared loop.

    ``config`` is the run's dataclass config (written as ``config.yaml``); ``input_size`` is the
    (H, W) its validation images are loaded at.
    """

    name: ClassVar[str]
    #: loss columns of log.csv, in order (the loop adds step, stage, elapsed_s and validation)
    log_columns: ClassVar[tuple[str, ...]] = ()
    config: Any
    input_size: tuple[int, int]

    def log(self, message: str) -> None:
        """A message of the method's (logged at INFO under its module's logger; the command
        line shows it on standard error, above a running progress bar)."""
        logging.getLogger(type(self).__module__).info(message)

    #: keys of :meth:`state` that differ between the ranks of a distributed run (their random
    #: streams); each rank's are saved, the rest is rank 0's. None: the whole state is per rank.
    rank_state_keys: ClassVar[tuple[str, ...] | None] = None

    @property
    def distributed(self) -> DistributedContext:
        """The process's distributed context (a no-op for a single process). A method calls
        ``self.distributed.average_gradients(optimizer)`` between ``backward()`` and
        ``optimizer.step()``, and seeds its data streams with ``self.distributed.rank_seed(seed)``."""
        return dist_module.current()

    @abstractmethod
    def modules(self) -> dict[str, torch.nn.Module]:
        """The modules whose weights make the model (saved in every checkpoint)."""

    @abstractmethod
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Optimisers whose state a resume needs."""

    @abstractmethod
    def loop_settings(self) -> LoopSettings: ...

    @abstractmethod
    def train_step(self, step: int) -> dict[str, float]:
        """One update on one mini-batch (``step`` is 0-based); returns the numbers to log."""

    def stage(self, step: int) -> str:
        """Name of the training stage of 0-based ``step`` (for the log and progress bar)."""
        return "train"

    def start(self) -> None:
        """Initialisation of a fresh run that depends on the data (not called on resume)."""

    def state(self) -> dict:
        """Everything besides weights and optimiser states needed to continue exactly
        (generators, caches): tensors, numbers, strings, lists and dicts of them."""
        return {}

    def load_state(self, state: dict) -> None:
        """Restore :meth:`state`."""

    def before_save(self) -> None:
        """Called before every checkpoint (e.g. NetVLAD fits its PCA here)."""

    def validation_vectors(self, images: torch.Tensor) -> np.ndarray:
        """uint8 (N, 3, H, W) -> (N, D) L2-normalised descriptors, for validation."""
        raise ConfigError(f"{self.name}: this method cannot validate during training")


def training_device(runtime) -> torch.device:
    """Apply a run's ``runtime`` section (every trained method has one, with the same names):
    ``runtime.threads`` torch CPU threads (0 = torch's default) and ``runtime.device`` resolved
    to a ``torch.device`` (``auto``: a GPU when there is one; a GPU that is not there is a
    ConfigError naming ``runtime.device``). The one place training picks its device and threads."""
    from fdnet.backbones import resolve_device

    if int(runtime.threads) > 0:
        torch.set_num_threads(int(runtime.threads))
    return resolve_device(runtime.device, where="runtime.device")


def training_precision(runtime, device: torch.device, native_only: bool = False) -> bool:
    """Whether the run computes its forward passes under bfloat16 autocast on ``device``:
    ``runtime.bf16``, and with ``native_only`` only where the device runs bf16 natively (a CPU
    without AVX-512 BF16/AMX emulates it slowly)."""
    from fdnet.backbones import bf16_native

    return bool(runtime.bf16) and (not native_only or bf16_native(device))


def autocast(device: torch.device, enabled: bool):
    """bfloat16 autocast on ``device``'s type (a no-op context when not ``enabled``)."""
    from fdnet.backbones import autocast as device_autocast

    return device_autocast(device, enabled)


def validation_metrics(method: TrainingMethod, data: ValidationImages) -> dict[str, float]:
    """R@1, R@5, R@100P and AUC (recall over queries with a match) of cosine matching."""
    from fdnet.metrics import evaluate_similarity

    reference = method.validation_vectors(data.reference)
    query = method.validation_vectors(data.query)
    metrics = evaluate_similarity(query @ reference.T, data.ground_truth, ns=(1, 5))
    return {
        "recall@1": metrics.recall_at_n[1],
        "recall@5": metrics.recall_at_n[5],
        "recall@100p": metrics.recall_at_100_precision,
        "auc": metrics.auc_pr,
    }


def numpy_rng_state(rng: np.random.Generator) -> str:
    """A numpy generator's state as a string for a checkpoint: PCG64's state holds 128-bit
    integers, which JSON keeps exact."""
    return json.dumps(rng.bit_generator.state)


def set_numpy_rng_state(rng: np.random.Generator, text: str) -> None:
    rng.bit_generator.state = json.loads(text)


class _StopRequest:
    """SIGINT handler that lets the current step finish (a half-applied optimiser step would
    leave weights and step counter out of sync); the loop then checkpoints and stops.

    Under torchrun SIGTERM is handled the same way: torchrun starts its workers in sessions of
    their own, so Ctrl-C (or a scheduler's SIGTERM) reaches torchrun alone, which passes the
    signal on to every worker and kills them 30 s later; the ranks agree to stop after the
    current step and rank 0 checkpoints within that time."""

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT,)) -> None:
        self.requested = False
        self._signals = signals
        self._previous: dict[int, Any] = {}

    def __enter__(self):
        for signum in self._signals:
            try:
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not in the main thread: signal handling stays Python's default
                pass
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:  # second Ctrl-C: give up waiting
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)


class _NoLog:
    """The log of ranks other than 0: they write nothing into the run directory."""

    def write(self, row: dict) -> None:
        pass

    def truncate_after(self, step: int) -> None:
        pass

    def close(self) -> None:
        pass


class Trainer:
    """Runs one :class:`TrainingMethod` into one run directory (see the module docstring).

    Use :func:`run_training`, which also holds the run directory's lock; the class is public for
    tests that step a run by hand. In a distributed run every rank builds a Trainer; rank 0 reads
    and writes the run directory, the others get what they need from it by broadcast.
    """

    def __init__(
        self,
        method: TrainingMethod,
        run_dir: str | Path,
        validation: ValidationImages | None = None,
        resume: bool = False,
        override: bool = False,
        tensorboard: bool = True,
        command: str = "",
    ) -> None:
        self.method = method
        self.run_dir = Path(run_dir)
        self.dist = method.distributed
        # validation, best/ and the log are rank 0's; the other ranks skip them in lockstep
        self.validation = validation if self.dist.is_main else None
        self.settings = method.loop_settings()
        for name in ("checkpoint_every", "log_every"):
            if getattr(self.settings, name) < 1:
                raise ConfigError(f"{method.name}: {name} must be >= 1")
        if self.settings.total_steps < 0:
            raise ConfigError(f"{method.name}: the number of training steps must be >= 0")
        self.step = 0
        self.elapsed = 0.0
        self.best = {"step": -1, "recall@1": -1.0, "auc": -1.0}
        self.last_validation: dict[str, float] = {}
        self.changes: list[str] = []
        self._saved_step = -1  # the step of the checkpoint on disk that this trainer's state matches
        if resume:
            self._resume(override, command)
        else:
            self.dist.collectively(self._check_fresh, main_only=True)
            self.dist.collectively(method.start)
            # identical initial weights everywhere (data-dependent starts, e.g. NetVLAD's k-means
            # on each rank's own sample, would otherwise differ)
            self._broadcast_weights()
        columns = ["step", "stage", "elapsed_s", *method.log_columns, "val_recall@1", "val_recall@100p"]

        def open_log():
            if not self.dist.is_main:
                return _NoLog()
            log = TrainingLog(self.run_dir, columns, tensorboard=tensorboard)
            if resume:
                log.truncate_after(self.step)
            return log

        self.log = self.dist.collectively(open_log)

    def _check_fresh(self) -> None:
        runs.check_run_state(self.run_dir, resume=False)

    def _broadcast_weights(self) -> None:
        for module in self.method.modules().values():
            self.dist.broadcast_module(module)

    # ------------------------------------------------------------------ checkpoints
    def _own_random_state(self) -> dict:
        """This rank's random streams: torch's RNG and the per-rank part of the method's state."""
        return {
            "torch_rng": torch.get_rng_state(),
            "method_state": dist_module.rank_part(self.method.state(), self.method.rank_state_keys),
        }

    def _state(self, rank_states: list | None = None) -> dict:
        state = {
            "step": self.step,
            "elapsed_seconds": self.elapsed,
            "stage": self.method.stage(max(self.step - 1, 0)),
            "torch_rng": torch.get_rng_state(),
            "best_step": self.best["step"],
            "best_recall@1": float(self.best["recall@1"]),
            "best_auc": float(self.best["auc"]),
            "method_state": self.method.state(),
            # how many processes trained it: a resume with another number is refused unless --override
            "world_size": self.dist.world_size,
        }
        if rank_states is not None:
            state["rank_states"] = rank_states  # every rank's random streams, rank order
        return state

    def save(self) -> Path:
        """Publish a checkpoint of the current step (in a distributed run: every rank calls it at
        the same step; rank 0 writes). A write that fails (a full disk, a lost mount) stops the
        run with the previous complete checkpoint still current."""
        # On every rank, so a model changed here (NetVLAD's PCA) stays the same on all of them.
        self.method.before_save()
        rank_states = self.dist.gather_to_main(self._own_random_state()) if self.dist.enabled else None
        published = self.dist.collectively(lambda: self._write(rank_states), main_only=True)
        self._saved_step = self.step
        return published

    def _write(self, rank_states: list | None) -> Path:
        try:
            return runs.save_checkpoint(
                self.run_dir,
                self.method.modules(),
                self.method.config,
                optimizers=self.method.optimizers(),
                state=self._state(rank_states),
            )
        except (OSError, ConfigError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            try:
                previous = runs.load_training_state(self.run_dir)["step"]
            except ConfigError:
                previous = None
            if previous is None:  # nothing to resume from: --resume would only say so
                message = (
                    f"{self.run_dir}: could not write the checkpoint of step {self.step} ({reason}); no "
                    "checkpoint was written before it, so there is nothing to resume: fix the cause "
                    "(e.g. free disk space) and run the same command again"
                )
            else:
                message = (
                    f"{self.run_dir}: could not write the checkpoint of step {self.step} ({reason}); "
                    f"the previous complete checkpoint (step {previous}) is intact: fix the cause "
                    "(e.g. free disk space) and continue with --resume"
                )
            # a full disk or a lost mount stays an operating-system error (OutputError is both)
            raise (output_error(message, exc) if isinstance(exc, OSError) else ConfigError(message)) from exc

    def _read_run(self, override: bool, command: str) -> dict:
        """Rank 0: check the resume and load weights and optimiser states from the run directory.
        Returns what every rank needs to continue (the other ranks receive it by broadcast)."""
        runs.check_run_state(self.run_dir, resume=True)
        saved = runs.load_config(self.run_dir, type(self.method.config))
        differences = runs.config_differences(saved, self.method.config)
        if differences and not override:
            raise ConfigError(
                f"{self.run_dir}: --resume asks for other settings than the run was trained with: "
                + "; ".join(differences)
                + ". Repeat the run's own settings, or add --override to continue with the new ones "
                "(the change is recorded in changes.yaml)"
            )
        runs.load_weights(self.run_dir, self.method.modules())
        state = runs.load_training_state(self.run_dir, self.method.optimizers())
        saved_world, world = int(state.get("world_size", 1)), self.dist.world_size
        if saved_world != world:
            if not override:
                raise ConfigError(
                    f"{self.run_dir}: the run was trained by {saved_world} process{'es' if saved_world > 1 else ''} "
                    f"(world size {saved_world}) and is resumed by {world} (world size {world}); that changes the "
                    f"effective batch and every process's random streams. Resume it with {saved_world} "
                    f"process{'es' if saved_world > 1 else ''} (torchrun --nproc-per-node/--nnodes"
                    f"{'' if saved_world > 1 else ', or plain fdnet'}), or add --override to continue with world size "
                    f"{world} (recorded in changes.yaml)"
                )
            differences = [*differences, f"world_size: saved {saved_world}, requested {world}"]
        if differences:
            runs.record_changes(self.run_dir, int(state["step"]), differences, command)
        optimizers = None
        if self.dist.enabled:  # for the other ranks (CPU copies: a CUDA tensor would unpickle onto cuda:0)
            optimizers = {name: _to_cpu(opt.state_dict()) for name, opt in self.method.optimizers().items()}
        return {"state": state, "changes": differences, "optimizers": optimizers}

    def _resume(self, override: bool, command: str) -> None:
        dist, method = self.dist, self.method
        fresh = method.state()  # this rank's own streams as seeded, for a rank the run has not seen
        payload = dist.collectively(lambda: self._read_run(override, command), main_only=True)
        if dist.enabled:
            self._broadcast_weights()
            if not dist.is_main:
                for name, opt in method.optimizers().items():
                    opt.load_state_dict(payload["optimizers"][name])
        state = payload["state"]
        self.step = int(state["step"])
        self._saved_step = self.step
        self.changes = list(payload["changes"])
        self.elapsed = float(state["elapsed_seconds"])
        self.best = {
            "step": int(state["best_step"]),
            "recall@1": float(state["best_recall@1"]),
            "auc": float(state.get("best_auc", -1.0)),
        }
        keys = method.rank_state_keys
        shared = state.get("method_state", {})
        # A single-process save has no rank_states: its top-level streams are rank 0's.
        saved_ranks = state.get("rank_states") or [
            {"torch_rng": state["torch_rng"], "method_state": dist_module.rank_part(shared, keys)}
        ]
        if dist.rank < len(saved_ranks):
            own = saved_ranks[dist.rank]
            torch.set_rng_state(own["torch_rng"])
            method_state = dist_module.merge_rank_state(shared, own["method_state"], keys)
        else:  # more processes than the run had (--override): this rank keeps its freshly seeded streams
            method_state = dist_module.merge_rank_state(shared, fresh, keys)
        dist.collectively(lambda: method.load_state(method_state))

    def save_stage_end(self, stage: str) -> None:
        """Keep the weights at the end of ``stage`` in ``RUN/stages/STAGE/`` (weights and config,
        loadable as ``--checkpoint RUN/stages/STAGE``), so what each stage did can be measured on
        any frames afterwards; rolling checkpoints keep only the newest."""
        self.method.before_save()
        self.dist.collectively(
            lambda: runs.save_weights(
                self.run_dir / STAGES_DIR / stage, self.method.modules(), self.method.config, step=self.step
            ),
            main_only=True,
        )

    # ------------------------------------------------------------------ validation
    def validate_now(self) -> dict[str, float]:
        metrics = validation_metrics(self.method, self.validation)
        self.last_validation = metrics
        # R@1 first; ties (frequent on small validation sets, where R@1 saturates) go to the
        # higher area under the PR curve, which keeps moving after R@1 has stopped.
        if (metrics["recall@1"], metrics["auc"]) > (self.best["recall@1"], self.best["auc"]):
            self.best = {"step": self.step, "recall@1": metrics["recall@1"], "auc": metrics["auc"]}
            best_dir = self.run_dir / BEST_DIR
            self.method.before_save()
            runs.save_weights(best_dir, self.method.modules(), self.method.config, step=self.step)
            lines = [f"step: {self.step}", f"validation: {self.validation.description!r}"]
            lines += [f"{k}: {v:.6f}" for k, v in metrics.items()]
            atomic_write_text(best_dir / "validation.yaml", "\n".join(lines) + "\n")
        return metrics

    # ------------------------------------------------------------------ loop
    def fit(self, max_minutes: float | None = None, progress: bool = True, since: float | None = None) -> dict:
        """Train until the schedule ends, ``max_minutes`` pass (counted from ``since``, a
        :func:`time.monotonic` time, default now: the command's start counts what came before
        training) or Ctrl-C; always checkpoint (after at least one step).

        Returns a summary dict (``status`` is "finished", "time limit" or "interrupted").
        Re-raises KeyboardInterrupt after saving when interrupted. In a distributed run every
        rank stops at the same step: a stop that any rank sees (its Ctrl-C or SIGTERM, its clock
        passing ``max_minutes``) is agreed on after every step.
        """
        method, settings, dist = self.method, self.settings, self.dist
        total = settings.total_steps
        validate_every = settings.validate_every if self.validation is not None else 0
        bar = None
        if progress and dist.is_main:
            from fdnet.progress import progress_bar

            bar = progress_bar(total=total, initial=self.step, unit="step")
        status = "finished"
        started = time.monotonic()
        since = started if since is None else since
        base_elapsed = self.elapsed
        interrupted = False
        signals = (signal.SIGINT, signal.SIGTERM) if dist.launched else (signal.SIGINT,)
        with _StopRequest(signals) as stop:
            while self.step < total:
                numbers = method.train_step(self.step)
                # weights stay identical through the averaged gradients; running statistics are
                # rank 0's on every rank after each step (DDP's broadcast_buffers)
                dist.broadcast_buffers(method.modules().values())
                self.step += 1
                self.elapsed = base_elapsed + time.monotonic() - started
                stage = method.stage(self.step - 1)
                row = None
                if validate_every and (self.step % validate_every == 0 or self.step == total):
                    metrics = self.validate_now()
                    row = {"val_recall@1": metrics["recall@1"], "val_recall@100p": metrics["recall@100p"]}
                if self.step % settings.log_every == 0 or row is not None or self.step == total:
                    self.log.write(
                        {
                            "step": self.step,
                            "stage": stage,
                            "elapsed_s": round(self.elapsed, 2),
                            **numbers,
                            **(row or {}),
                        }
                    )
                if self.step % settings.checkpoint_every == 0:
                    self.save()
                if self.step == total or method.stage(self.step) != stage:
                    self.save_stage_end(stage)
                if bar is not None:  # this step's numbers first, so the update shows them
                    shown = {k[:5]: f"{v:.3g}" for k, v in numbers.items()}
                    if self.last_validation:
                        shown["valR@1"] = f"{self.last_validation['recall@1']:.3f}"
                    bar.set_description(stage, refresh=False)
                    bar.set_postfix(shown, refresh=False)
                    bar.update(1)
                out_of_time = max_minutes is not None and time.monotonic() - since >= max_minutes * 60.0
                stop_now, out_of_time = dist.agree(stop.requested, out_of_time)
                if stop_now:
                    status, interrupted = "interrupted", True
                    break
                if out_of_time:
                    status = "time limit"
                    break
        if bar is not None:
            bar.close()
        if self._saved_step != self.step:
            self.save()
        self.log.close()
        summary = {
            "status": status,
            "step": self.step,
            "total_steps": total,
            "elapsed_seconds": self.elapsed,
            "run_dir": str(self.run_dir),
            "best_step": self.best["step"],
            "best_recall@1": self.best["recall@1"],
            "changes": list(self.changes),
            "world_size": dist.world_size,
        }
        if interrupted:
            raise KeyboardInterrupt(summary)
        return summary


def _to_cpu(value):
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: _to_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_to_cpu(v) for v in value)
    return value


def run_training(
    build: Callable[[], tuple[TrainingMethod, ValidationImages | None]],
    run_dir: str | Path,
    resume: bool = False,
    override: bool = False,
    max_minutes: float | None = None,
    progress: bool = True,
    command: str = "fdnet train",
    runtime=None,
) -> dict:
    """Train the method ``build()`` returns (with its validation images, or None) into ``run_dir``.

    ``runtime``: the run config's ``runtime`` section; its threads are set and its device checked
    here, before the lock is taken (the method resolves the same device with :func:`training_device`).

    The run directory's lock is taken, and a fresh run's or a resume's precondition checked,
    before ``build`` reads any image, so a second training on the same folder fails at once.

    Started by torchrun (``WORLD_SIZE`` etc. in the environment), this joins the process group
    unless the caller already did (:func:`fdnet.training.distributed.launch`). Rank 0 alone takes
    the lock and checks the preconditions, for the whole run; the other ranks never touch the
    lock file (they would only queue behind rank 0). Whatever fails on one rank, there or while
    building, stops every rank with its message.
    """
    run_dir = Path(run_dir)
    since = time.monotonic()  # --max-minutes counts from here: reading images and choosing a start too
    if runtime is not None:  # settings errors (a GPU that is not there) before the lock and any image
        training_device(runtime)
    with dist_module.launch() as dist, contextlib.ExitStack() as held:

        def take_lock() -> None:
            ensure_writable(run_dir, what="run directory", directory=True)
            held.enter_context(runs.RunLock(run_dir, command=command))
            runs.check_run_state(run_dir, resume)

        dist.collectively(take_lock, main_only=True)

        def build_here():
            method, validation = build()
            dist.check_device(getattr(method, "device", None))
            return method, validation

        method, validation = dist.collectively(build_here)
        trainer = Trainer(method, run_dir, validation=validation, resume=resume, override=override, command=command)
        return trainer.fit(max_minutes=max_minutes, progress=progress, since=since)
