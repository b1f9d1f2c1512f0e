"""Crash-safe run directories: checkpoint generations, a run lock and a record of resumed changes.

A run directory is self-describing (a model loads from nothing but its path) and survives kill -9,
Ctrl-C, power loss and a full disk during a save::

    RUN_DIR/
      .lock                       held (flock) while a training writes here; pid, host, command
      changes.yaml                settings changed on ``--resume --override``, with the step
      checkpoints/
        step-000001000/           one generation = one unit, written together, published together
          model.safetensors       weights of every named module ("<module>.<param>" keys)
          training_state.pt       optimiser states + resume state (absent in weights-only ones)
          config.yaml             the dataclass config that built the model
        step-000002000/           the newest complete generation is the current one
        .tmp-2100-<id>/           a save in progress (or a crashed one, removed at the next save)

A generation is written completely into a ``.tmp-*`` folder beside the others, every file and the
folder fsynced and read back, then published by one ``rename`` (atomic on POSIX) and the parent
folder fsynced. Until that rename the previous generation is untouched and current; older ones
beyond ``keep`` are removed only after the new one is published. Every file of a generation
carries the same ``save_id`` (weights metadata, training state, a comment line in config.yaml),
so a reader can prove the three belong together. Readers take the newest generation that is
complete (:func:`latest_checkpoint`); folders starting with "." are never read. Every load
function accepts a run directory or a generation folder.

The package, by concern: :mod:`~fdnet.runs.checkpoints` (the generations: save, find),
:mod:`~fdnet.runs.loading` (read the current one back: config, weights, training state),
:mod:`~fdnet.runs.lock` (:class:`RunLock`) and :mod:`~fdnet.runs.changes` (``changes.yaml``).
Its modules must not import :mod:`fdnet.training`: inference code loads trained models with them.
"""

from fdnet.runs.changes import CHANGES_FILE, read_changes, record_changes
from fdnet.runs.checkpoints import (
    BEST_DIR,
    CHECKPOINTS_DIR,
    CONFIG_FILE,
    FORMAT_VERSION,
    KIND_TRAINING,
    KIND_WEIGHTS,
    STATE_FILE,
    WEIGHTS_FILE,
    check_run_state,
    is_run,
    latest_checkpoint,
    recorded_method,
    save_checkpoint,
    save_weights,
    weights_folder,
    weights_note,
)
from fdnet.runs.loading import config_differences, load_config, load_training_state, load_weights
from fdnet.runs.lock import LOCK_FILE, RunLock

__all__ = [
    "BEST_DIR",
    "recorded_method",
    "weights_folder",
    "weights_note",
    "CHANGES_FILE",
    "CHECKPOINTS_DIR",
    "CONFIG_FILE",
    "FORMAT_VERSION",
    "KIND_TRAINING",
    "KIND_WEIGHTS",
    "LOCK_FILE",
    "STATE_FILE",
    "WEIGHTS_FILE",
    "RunLock",
    "check_run_state",
    "config_differences",
    "is_run",
    "latest_checkpoint",
    "load_config",
    "load_training_state",
    "load_weights",
    "read_changes",
    "record_changes",
    "save_checkpoint",
    "save_weights",
]
