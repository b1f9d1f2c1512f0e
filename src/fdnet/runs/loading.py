"""Reading a run's current checkpoint back: its config (and how a saved config differs from a
requested one), its weights into modules, its training state and optimiser states for a resume.
Each reader takes the newest complete generation (:func:`fdnet.runs.checkpoints.latest_checkpoint`)
and accepts a run directory or a generation folder.

This module must not import :mod:`fdnet.training`: inference code loads trained models with it.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path
from typing import Any, Mapping, TypeVar

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from fdnet.config import flatten_dotted, load_yaml, to_dict
from fdnet.errors import ConfigError
from fdnet.runs.checkpoints import (
    CONFIG_FILE,
    KIND_WEIGHTS,
    STATE_FILE,
    WEIGHTS_FILE,
    latest_checkpoint,
    read_weights_metadata,
)
from fdnet.runs.checksums import verify_state, verify_tensors

T = TypeVar("T")


def _with_latest(run_dir: str | Path, read):
    """``read(latest_checkpoint(run_dir))``, resolved again if a concurrent save pruned the folder
    between choosing it and reading it (a reader never blocks a training)."""
    for attempt in range(3):
        folder = latest_checkpoint(run_dir)
        try:
            return read(folder)
        except OSError as exc:
            if folder.is_dir() or attempt == 2:
                raise ConfigError(f"{folder}: cannot read the checkpoint ({exc.strerror or exc})") from exc
        except ConfigError:
            if folder.is_dir() or attempt == 2:
                raise


def load_config(run_dir: str | Path, cls: type[T]) -> T:
    """Read the current checkpoint's config.yaml into dataclass ``cls`` (unknown keys are a
    ConfigError naming the file)."""
    return _with_latest(run_dir, lambda folder: load_yaml(cls, folder / CONFIG_FILE))


def config_differences(saved: Any, requested: Any, keys: list[str] | None = None) -> list[str]:
    """``"a.b: saved X, requested Y"`` for every differing setting (only dotted ``keys`` if given)."""
    a, b = (flatten_dotted(to_dict(d) if dataclasses.is_dataclass(d) else dict(d)) for d in (saved, requested))
    names = keys if keys is not None else sorted(set(a) | set(b))
    return [f"{k}: saved {a.get(k)!r}, requested {b.get(k)!r}" for k in names if a.get(k) != b.get(k)]


def _load_weights_from(
    folder: Path, modules: Mapping[str, torch.nn.Module], device: str | torch.device
) -> dict[str, str]:
    path = folder / WEIGHTS_FILE
    try:
        tensors = load_file(str(path), device=str(device))
        metadata = read_weights_metadata(path)
    except FileNotFoundError:
        raise
    except (SafetensorError, OSError) as exc:
        raise ConfigError(f"{path}: cannot read weights ({exc})") from exc
    verify_tensors(path, tensors, metadata)
    for name, module in modules.items():
        prefix = f"{name}."
        own = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
        if not own:
            saved = metadata.get("modules", "?")
            raise ConfigError(f"{path}: has no weights for module {name!r} (it holds: {saved})")
        expected = module.state_dict()
        missing = sorted(set(expected) - set(own))
        extra = sorted(set(own) - set(expected))
        if missing or extra:
            raise ConfigError(
                f"{path}: module {name!r} does not match the checkpoint "
                f"(missing {missing[:3]}{'...' if len(missing) > 3 else ''}, "
                f"unexpected {extra[:3]}{'...' if len(extra) > 3 else ''}); "
                "the run was trained with other architecture settings"
            )
        for key, value in expected.items():
            if tuple(value.shape) != tuple(own[key].shape):
                raise ConfigError(
                    f"{path}: {name}.{key} has shape {tuple(own[key].shape)} in the checkpoint but "
                    f"{tuple(value.shape)} in the model; the run was trained with other settings "
                    "(input size, widths, vector length or trunk block: the model settings in its config.yaml)"
                )
    # Only after every module matched, so a mismatch leaves all modules as they were.
    for name, module in modules.items():
        prefix = f"{name}."
        module.load_state_dict({k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}, strict=True)
    metadata["checkpoint"] = str(folder)
    return metadata


def load_weights(
    run_dir: str | Path, modules: Mapping[str, torch.nn.Module], device: str | torch.device = "cpu"
) -> dict[str, str]:
    """Load the current checkpoint's weights into ``modules`` (all must be present, with the same
    tensor names and shapes). Returns the weights' metadata: ``step``, ``save_id``, ``modules``,
    ``kind`` and ``checkpoint`` (the folder read)."""
    return _with_latest(run_dir, lambda folder: _load_weights_from(folder, modules, device))


def _load_training_state_from(folder: Path, optimizers: Mapping[str, torch.optim.Optimizer] | None) -> dict[str, Any]:
    path = folder / STATE_FILE
    if not path.is_file():
        try:
            kind = read_weights_metadata(folder / WEIGHTS_FILE).get("kind")
        except (SafetensorError, OSError):
            kind = None
        what = "a weights-only checkpoint" if kind == KIND_WEIGHTS else f"no {STATE_FILE}"
        raise ConfigError(f"{folder}: {what}; this run cannot be resumed (final, best or exported weights)")
    try:
        weights_metadata = read_weights_metadata(folder / WEIGHTS_FILE)
    except (SafetensorError, OSError) as exc:
        raise ConfigError(f"{folder / WEIGHTS_FILE}: cannot read weights ({exc})") from exc
    weights_id = weights_metadata.get("save_id")
    try:
        data = path.read_bytes()
        verify_state(path, data, weights_metadata)
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except (FileNotFoundError, ConfigError):
        raise
    except Exception as exc:  # torch raises several types for a corrupt or foreign file
        raise ConfigError(f"{path}: cannot read training state ({exc.__class__.__name__}: {exc})") from exc
    if weights_id != payload.get("save_id"):
        raise ConfigError(
            f"{path}: training state and {WEIGHTS_FILE} come from different saves "
            "(interrupted while checkpointing?); cannot resume exactly"
        )
    saved_optimizers = payload.get("optimizers", {})
    for name, opt in (optimizers or {}).items():
        if name not in saved_optimizers:
            raise ConfigError(f"{path}: no optimiser state for {name!r} (has: {', '.join(saved_optimizers) or 'none'})")
        try:
            opt.load_state_dict(saved_optimizers[name])
        except (ValueError, KeyError) as exc:
            raise ConfigError(f"{path}: optimiser state for {name!r} does not fit this optimiser ({exc})") from exc
    return payload["state"]


def load_training_state(
    run_dir: str | Path, optimizers: Mapping[str, torch.optim.Optimizer] | None = None
) -> dict[str, Any]:
    """Return the current checkpoint's resume ``state`` dict and load the saved optimiser states
    into ``optimizers``. ConfigError when the checkpoint is weights-only, or when its training
    state belongs to a different save than its weights."""
    return _with_latest(run_dir, lambda folder: _load_training_state_from(folder, optimizers))
