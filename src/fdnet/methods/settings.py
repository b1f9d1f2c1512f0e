"""Settings every trained method shares: which images it trains on, how it validates, where it
runs (``runtime``) and, for the methods that choose an optimiser by name, ``optim``.

Each method's run config (``FDNetRunConfig``, ``CALCRunConfig``, ``NetVLADRunConfig``, in
``fdnet.methods.<name>.config``) holds these beside its own model and training settings, and is
written to ``RUN_DIR/config.yaml``. This module is plain dataclasses (no torch, no training code),
so inference can read a run's config.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass
class DataConfig:
    """Which images a run trains on (recorded in the run; ``--resume`` reads the same ones)."""

    #: dataset folder (one sub-folder per condition, or a published layout with dataset_format)
    root: str = ""
    #: conditions (sub-folders) to train on; empty = all of them
    conditions: tuple[str, ...] = ()
    #: "START:END" slice of every condition used for training ("" = all frames)
    frames: str = ""
    #: a published layout read by ``fdnet.data.formats`` ("" = one sub-folder per condition)
    dataset_format: str = ""
    #: with ``dataset_format``: a named split ("train", "test", "all") or "START:END" ("" = the
    #: format's training default)
    split: str = ""


@dataclass
class RuntimeConfig:
    """Where and how a run computes, and how often it writes: the same ``runtime.*`` settings for
    every trained method (the training loop applies them, :func:`fdnet.training.loop.training_device`)."""

    seed: int = 0
    #: "auto" (a GPU when there is one, else the CPU), "cpu", "cuda" or "cuda:N"
    device: str = "auto"
    #: torch CPU threads (0 = leave torch's default)
    threads: int = 0
    #: bfloat16 autocast for the forward passes (losses stay float32)
    bf16: bool = False
    #: write a resumable checkpoint every N steps (and always at the end / on Ctrl-C)
    checkpoint_every: int = 250
    #: append losses to log.csv every N steps
    log_every: int = 50


@dataclass
class OptimizerConfig:
    """The optimiser of the methods that choose one by name (``optim.*``)."""

    #: "adam" or "sgd" (momentum and weight_decay apply to sgd)
    optimizer: str = "adam"
    lr: float = 1e-3
    momentum: float = 0.9
    weight_decay: float = 0.0


class StepsInTrainSection:
    """What the run configs of the methods that count their steps in ``train.steps`` (CALC,
    NetVLAD) share: ``--steps`` sets ``train.steps``."""

    @property
    def total_steps(self) -> int:
        return self.train.steps

    def with_total_steps(self, steps: int):
        return dataclasses.replace(self, train=dataclasses.replace(self.train, steps=int(steps)))


@dataclass
class ValidationConfig:
    """Optional periodic validation: R@1 of reference vs query condition on held-out frames.

    It uses place correspondences (frame-aligned ground truth) of the validation frames only to
    pick the best checkpoint (``best/``); training itself never sees them. Keep these frames out
    of any test split you report.
    """

    reference: str = ""
    query: str = ""
    frames: str = ""
    tolerance: int = 0
    every: int = 250


def check_finite(name: str, value, positive: bool = False) -> None:
    """A numeric setting must be a finite number (``--set optim.lr=nan`` would otherwise train
    silently into NaN weights); ``positive``: also > 0, else >= 0."""
    from fdnet.errors import ConfigError

    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: expected a number, got {value!r}") from exc
    if number != number or number in (float("inf"), float("-inf")):
        raise ConfigError(f"{name}: must be a finite number, got {value!r}")
    if positive and number <= 0:
        raise ConfigError(f"{name}: must be > 0, got {value!r}")
    if not positive and number < 0:
        raise ConfigError(f"{name}: must be >= 0, got {value!r}")


def check_validation_pair(validation: ValidationConfig) -> None:
    """Validation needs a reference and a query condition, or neither."""
    from fdnet.errors import ConfigError

    if bool(validation.reference) != bool(validation.query):
        raise ConfigError("validation: give both a reference and a query condition (or neither)")
    if validation.reference and validation.reference == validation.query:
        raise ConfigError(
            f"validation: the reference and the query are the same condition "
            f"({validation.reference!r}); every image would match itself, so the scores would "
            "say nothing: choose two conditions"
        )
