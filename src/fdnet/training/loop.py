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
* ``log.csv`` (rows after the resumed checkpoint are dropped) and a progress bar.
"""

from __future__ import annotations

import json
import signal
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np
import torch

from fdnet import runs
from fdnet.errors import ConfigError
from fdnet.io import atomic_write_text, ensure_writable
from fdnet.training.data import ValidationImages
from fdnet.training.logging import TrainingLog

BEST_DIR = "best"


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
    #: where the method's messages go (the loop points it at the progress bar's writer)
    log: Callable[[str], None] = print

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


def validation_metrics(method: TrainingMethod, data: ValidationImages) -> dict[str, float]:
    """R@1, R@5, R@100P and AUC (recall over queries with a match) of cosine matching."""
    from fdnet.evaluation.metrics import evaluate_similarity

    reference = method.validation_vectors(data.reference)
    query = method.validation_vectors(data.query)
    metrics = evaluate_similarity(query @ reference.T, data.ground_truth, ns=(1, 5))
    return {"recall@1": metrics.recall_at_n[1], "recall@5": metrics.recall_at_n[5],
            "recall@100p": metrics.recall_at_100_precision, "auc": metrics.auc_pr}


def numpy_rng_state(rng: np.random.Generator) -> str:
    """A numpy generator's state as a string for a checkpoint: PCG64's state holds 128-bit
    integers, which JSON keeps exact."""
    return json.dumps(rng.bit_generator.state)


def set_numpy_rng_state(rng: np.random.Generator, text: str) -> None:
    rng.bit_generator.state = json.loads(text)


class _StopRequest:
    """SIGINT handler that lets the current step finish (a half-applied optimiser step would
    leave weights and step counter out of sync); the loop then checkpoints and stops."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None

    def __enter__(self):
        try:
            self._previous = signal.signal(signal.SIGINT, self._handle)
        except ValueError:  # not in the main thread: Ctrl-C handling stays Python's default
            self._previous = None
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:  # second Ctrl-C: give up waiting
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


class Trainer:
    """Runs one :class:`TrainingMethod` into one run directory (see the module docstring).

    Use :func:`run_training`, which also holds the run directory's lock; the class is public for
    tests that step a run by hand.
    """

    def __init__(self, method: TrainingMethod, run_dir: str | Path, validation: ValidationImages | None = None,
                 resume: bool = False, override: bool = False, tensorboard: bool = True,
                 command: str = "") -> None:
        self.method = method
        self.run_dir = Path(run_dir)
        self.validation = validation
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
        if resume:
            self._resume(override, command)
        elif runs.is_run(self.run_dir):
            raise ConfigError(f"{self.run_dir}: already holds a run; use --resume to continue it or choose another --out")
        else:
            method.start()
        columns = ["step", "stage", "elapsed_s", *method.log_columns, "val_recall@1", "val_recall@100p"]
        self.log = TrainingLog(self.run_dir, columns, tensorboard=tensorboard)
        if resume:
            self.log.truncate_after(self.step)

    # ------------------------------------------------------------------ checkpoints
    def _state(self) -> dict:
        return {
            "step": self.step,
            "elapsed_seconds": self.elapsed,
            "stage": self.method.stage(max(self.step - 1, 0)),
            "torch_rng": torch.get_rng_state(),
            "best_step": self.best["step"],
            "best_recall@1": float(self.best["recall@1"]),
            "best_auc": float(self.best["auc"]),
            "method_state": self.method.state(),
        }

    def save(self) -> Path:
        """Publish a checkpoint of the current step. A write that fails (a full disk, a lost
        mount) stops the run with the previous complete checkpoint still current."""
        self.method.before_save()
        try:
            return runs.save_checkpoint(self.run_dir, self.method.modules(), self.method.config,
                                        optimizers=self.method.optimizers(), state=self._state())
        except (OSError, ConfigError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            try:
                previous = f"step {runs.load_training_state(self.run_dir)['step']}"
            except ConfigError:
                previous = "none yet"
            raise ConfigError(f"{self.run_dir}: could not write the checkpoint of step {self.step} ({reason}); "
                              f"the previous complete checkpoint ({previous}) is intact: fix the cause "
                              "(e.g. free disk space) and continue with --resume") from None

    def _resume(self, override: bool, command: str) -> None:
        if not runs.is_run(self.run_dir):
            raise ConfigError(f"{self.run_dir}: nothing to resume (no complete checkpoint); start a new run without --resume")
        saved = runs.load_config(self.run_dir, type(self.method.config))
        differences = runs.config_differences(saved, self.method.config)
        if differences and not override:
            raise ConfigError(
                f"{self.run_dir}: --resume asks for other settings than the run was trained with: "
                + "; ".join(differences)
                + ". Repeat the run's own settings, or add --override to continue with the new ones "
                "(the change is recorded in changes.yaml)")
        runs.load_weights(self.run_dir, self.method.modules())
        state = runs.load_training_state(self.run_dir, self.method.optimizers())
        self.step = int(state["step"])
        if differences:
            runs.record_changes(self.run_dir, self.step, differences, command)
            self.changes = differences
        self.elapsed = float(state["elapsed_seconds"])
        torch.set_rng_state(state["torch_rng"])
        self.best = {"step": int(state["best_step"]), "recall@1": float(state["best_recall@1"]),
                     "auc": float(state.get("best_auc", -1.0))}
        self.method.load_state(state.get("method_state", {}))

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
    def fit(self, max_minutes: float | None = None, progress: bool = True) -> dict:
        """Train until the schedule ends, ``max_minutes`` pass or Ctrl-C; always checkpoint.

        Returns a summary dict (``status`` is "finished", "time limit" or "interrupted").
        Re-raises KeyboardInterrupt after saving when interrupted.
        """
        method, settings = self.method, self.settings
        total = settings.total_steps
        validate_every = settings.validate_every if self.validation is not None else 0
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, initial=self.step, unit="step", dynamic_ncols=True)
            method.log = tqdm.write
        status = "finished"
        started = time.monotonic()
        base_elapsed = self.elapsed
        last_saved = self.step if runs.is_run(self.run_dir) else -1
        interrupted = False
        with _StopRequest() as stop:
            while self.step < total:
                numbers = method.train_step(self.step)
                self.step += 1
                self.elapsed = base_elapsed + time.monotonic() - started
                stage = method.stage(self.step - 1)
                row = None
                if validate_every and (self.step % validate_every == 0 or self.step == total):
                    metrics = self.validate_now()
                    row = {"val_recall@1": metrics["recall@1"], "val_recall@100p": metrics["recall@100p"]}
                if self.step % settings.log_every == 0 or row is not None or self.step == total:
                    self.log.write({"step": self.step, "stage": stage, "elapsed_s": round(self.elapsed, 2),
                                    **numbers, **(row or {})})
                if self.step % settings.checkpoint_every == 0:
                    self.save()
                    last_saved = self.step
                if bar is not None:
                    bar.update(1)
                    shown = {k[:5]: f"{v:.3g}" for k, v in numbers.items()}
                    if self.last_validation:
                        shown["valR@1"] = f"{self.last_validation['recall@1']:.3f}"
                    bar.set_description(stage)
                    bar.set_postfix(shown, refresh=False)
                if stop.requested:
                    status, interrupted = "interrupted", True
                    break
                if max_minutes is not None and time.monotonic() - started >= max_minutes * 60.0:
                    status = "time limit"
                    break
        if bar is not None:
            bar.close()
            method.log = print
        if last_saved != self.step:
            self.save()
        self.log.close()
        summary = {"status": status, "step": self.step, "total_steps": total,
                   "elapsed_seconds": self.elapsed, "run_dir": str(self.run_dir),
                   "best_step": self.best["step"], "best_recall@1": self.best["recall@1"],
                   "changes": list(self.changes)}
        if interrupted:
            raise KeyboardInterrupt(summary)
        return summary


def run_training(build: Callable[[], tuple[TrainingMethod, ValidationImages | None]], run_dir: str | Path,
                 resume: bool = False, override: bool = False, max_minutes: float | None = None,
                 progress: bool = True, command: str = "fdnet train") -> dict:
    """Train the method ``build()`` returns (with its validation images, or None) into ``run_dir``.

    The run directory's lock is taken, and a fresh run's or a resume's precondition checked,
    before ``build`` reads any image, so a second training on the same folder fails at once.
    """
    run_dir = Path(run_dir)
    ensure_writable(run_dir, what="run directory", directory=True)
    with runs.RunLock(run_dir, command=command):
        if resume and not runs.is_run(run_dir):
            raise ConfigError(f"{run_dir}: nothing to resume (no complete checkpoint); start a new run without --resume")
        if not resume and runs.is_run(run_dir):
            raise ConfigError(f"{run_dir}: already holds a run; use --resume to continue it or choose another --out")
        method, validation = build()
        trainer = Trainer(method, run_dir, validation=validation, resume=resume, override=override,
                          command=command)
        return trainer.fit(max_minutes=max_minutes, progress=progress)
