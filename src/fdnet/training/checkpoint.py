"""Run directories: trained weights + the config that built them + the state to resume.

A run directory is self-describing, so a user can load a model with nothing but its path::

    RUN_DIR/
      config.yaml             the dataclass config (fdnet.config), human-readable
      model.safetensors       weights of every named module, "<module>.<param>" keys (safetensors:
                              no pickle, safe to load from anyone)
      training_state.pt       optimiser states, step counters, RNG states, best-validation info;
                              internal resume state only, plain tensors/dicts read back with
                              ``torch.load(weights_only=True)`` (no arbitrary code)

Every file is written atomically (temporary file + rename), weights and training state first and
the config last. Each write stamps the same ``save_id`` into the weights' metadata and the
training state, so :func:`load_training_state` can tell when a crash left the two from different
saves and refuses to resume from a mismatched pair.

The API is deliberately small and model-agnostic (FDNet, CALC and NetVLAD all use it):

* :func:`save_run` writes a run (or a ``best/`` sub-run without optimiser state);
* :func:`load_config` reads ``config.yaml`` back into its dataclass;
* :func:`check_config` compares the saved config with the one a caller is about to use;
* :func:`load_weights` fills named modules, with a :class:`~fdnet.errors.ConfigError` naming the
  module and tensor when names or shapes do not match (= the run was trained with other settings);
* :func:`load_training_state` returns the resume state and restores optimiser states.
"""

from __future__ import annotations

import dataclasses
import io
import uuid
from pathlib import Path
from typing import Any, Mapping, TypeVar

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from fdnet.config import load_yaml, save_yaml, to_dict
from fdnet.errors import ConfigError
from fdnet.io import atomic_path, atomic_write_bytes

T = TypeVar("T")

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.yaml"
STATE_FILE = "training_state.pt"
FORMAT_VERSION = "1"


def _flatten_weights(modules: Mapping[str, torch.nn.Module]) -> dict[str, torch.Tensor]:
    tensors: dict[str, torch.Tensor] = {}
    for name, module in modules.items():
        if "." in name:
            raise ValueError(f"module name {name!r} must not contain '.'")
        for key, value in module.state_dict().items():
            # clone(): safetensors refuses tensors that share storage (tied weights, views).
            tensors[f"{name}.{key}"] = value.detach().to("cpu").contiguous().clone()
    return tensors


def save_run(
    run_dir: str | Path,
    modules: Mapping[str, torch.nn.Module],
    config: Any,
    optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
    state: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``modules``' weights, ``config`` and (optionally) resume state into ``run_dir``.

    ``config`` is a dataclass (saved with :func:`fdnet.config.save_yaml`) or a plain dict.
    ``state`` holds anything else needed to resume (step counters, stage, RNG states, best
    validation score): tensors, numbers, strings, lists and dicts of them only, so that it can be
    read back with ``weights_only=True``. When both ``optimizers`` and ``state`` are None no
    training-state file is written (an existing one is removed, so a stale resume state is never
    paired with new weights).
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_id = uuid.uuid4().hex
    metadata = {
        "format": f"fdnet-run/{FORMAT_VERSION}",
        "modules": ",".join(modules),
        "config_class": type(config).__name__,
        "save_id": save_id,
    }
    if state is not None and "step" in state:
        metadata["step"] = str(state["step"])

    with atomic_path(run_dir / WEIGHTS_FILE) as tmp:
        save_file(_flatten_weights(modules), str(tmp), metadata=metadata)

    state_path = run_dir / STATE_FILE
    if optimizers is None and state is None:
        state_path.unlink(missing_ok=True)
    else:
        payload = {
            "format": FORMAT_VERSION,
            "save_id": save_id,
            "optimizers": {name: opt.state_dict() for name, opt in (optimizers or {}).items()},
            "state": dict(state or {}),
        }
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        atomic_write_bytes(state_path, buffer.getvalue())

    if dataclasses.is_dataclass(config):
        save_yaml(config, run_dir / CONFIG_FILE)
    else:
        save_yaml(dict(config), run_dir / CONFIG_FILE)
    return run_dir


def _require_run(run_dir: Path) -> None:
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: run directory not found")
    if not (run_dir / WEIGHTS_FILE).is_file():
        raise ConfigError(f"{run_dir}: not a run directory (no {WEIGHTS_FILE}; expected the --out folder of a training run)")


def load_config(run_dir: str | Path, cls: type[T]) -> T:
    """Read ``run_dir/config.yaml`` into dataclass ``cls`` (unknown keys are a ConfigError)."""
    run_dir = Path(run_dir)
    _require_run(run_dir)
    return load_yaml(cls, run_dir / CONFIG_FILE)


def config_differences(saved: Any, requested: Any, keys: list[str] | None = None) -> list[str]:
    """``"a.b: saved X, requested Y"`` for every differing setting (only dotted ``keys`` if given)."""
    def flat(d: Any, prefix: str = "") -> dict[str, Any]:
        d = to_dict(d) if dataclasses.is_dataclass(d) else d
        out: dict[str, Any] = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out.update(flat(v, f"{prefix}{k}."))
            else:
                out[f"{prefix}{k}"] = v
        return out

    a, b = flat(saved), flat(requested)
    names = keys if keys is not None else sorted(set(a) | set(b))
    return [f"{k}: saved {a.get(k)!r}, requested {b.get(k)!r}" for k in names if a.get(k) != b.get(k)]


def check_config(run_dir: str | Path, saved: Any, requested: Any, keys: list[str] | None = None) -> None:
    """Raise ConfigError listing the settings where ``requested`` differs from ``saved``."""
    diffs = config_differences(saved, requested, keys)
    if diffs:
        raise ConfigError(
            f"{Path(run_dir) / CONFIG_FILE}: the checkpoint was trained with other settings than requested ("
            + "; ".join(diffs) + ")"
        )


def load_weights(run_dir: str | Path, modules: Mapping[str, torch.nn.Module],
                 device: str | torch.device = "cpu") -> dict[str, str]:
    """Load ``run_dir/model.safetensors`` into ``modules`` (all of them must be present, with the
    same tensor names and shapes). Returns the file's metadata (``step``, ``save_id``...)."""
    run_dir = Path(run_dir)
    _require_run(run_dir)
    path = run_dir / WEIGHTS_FILE
    try:
        tensors = load_file(str(path), device=str(device))
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as handle:
            metadata = dict(handle.metadata() or {})
    except (SafetensorError, OSError) as exc:
        raise ConfigError(f"{path}: cannot read weights ({exc})") from None
    for name, module in modules.items():
        prefix = f"{name}."
        own = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
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
                    "(input size, widths or vector length)"
                )
        module.load_state_dict(own, strict=True)
    return metadata


def load_training_state(run_dir: str | Path,
                        optimizers: Mapping[str, torch.optim.Optimizer] | None = None) -> dict[str, Any]:
    """Return the saved resume ``state`` dict; load the saved optimiser states into ``optimizers``.

    Raises ConfigError when the run has no training state, or when it belongs to a different save
    than the weights (a crash between the two writes).
    """
    run_dir = Path(run_dir)
    _require_run(run_dir)
    path = run_dir / STATE_FILE
    if not path.is_file():
        raise ConfigError(f"{run_dir}: no {STATE_FILE}; this run cannot be resumed (final or best-only weights)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a corrupt or foreign file
        raise ConfigError(f"{path}: cannot read training state ({exc.__class__.__name__}: {exc})") from None
    from safetensors import safe_open

    with safe_open(str(run_dir / WEIGHTS_FILE), framework="pt") as handle:
        weights_id = (handle.metadata() or {}).get("save_id")
    if weights_id != payload.get("save_id"):
        raise ConfigError(
            f"{path}: training state and {WEIGHTS_FILE} come from different saves "
            "(interrupted while checkpointing?); cannot resume exactly"
        )
    for name, opt in (optimizers or {}).items():
        if name not in payload["optimizers"]:
            raise ConfigError(f"{path}: no optimiser state for {name!r} (has: {', '.join(payload['optimizers'])})")
        opt.load_state_dict(payload["optimizers"][name])
    return payload["state"]
