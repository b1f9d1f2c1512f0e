"""Checkpoint generations of a run directory: how one is written (into a ``.tmp-*`` folder,
every file fsynced and read back, published by one rename) and found (the newest complete one);
:mod:`fdnet.runs.loading` reads one back (weights, training state, config). See :mod:`fdnet.runs`
for the layout on disk.

This module must not import :mod:`fdnet.training`: inference code loads trained models with it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import logging
import operator
import os
import re
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterator, Mapping, TypeVar

import torch
import yaml
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as safetensors_bytes

from fdnet.config import read_yaml_file, to_dict
from fdnet.errors import ConfigError, output_error
from fdnet.io import fsync_directory
from fdnet.runs.checksums import STATE_KEY, TENSORS_KEY, bytes_sha256, tensors_sha256

try:
    import fcntl
except ImportError:  # Windows: loading runs works; saves are not serialised (see _save_lock)
    fcntl = None

T = TypeVar("T")

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.yaml"
STATE_FILE = "training_state.pt"
CHECKPOINTS_DIR = "checkpoints"
FORMAT_VERSION = "2"

# Generation kinds, stored in the weights' metadata: a "weights" generation has no training state
# on purpose (best/, exports), so a missing training_state.pt is not a sign of a broken save.
KIND_TRAINING = "training"
KIND_WEIGHTS = "weights"

_TMP_PREFIX = ".tmp-"
_TRASH_PREFIX = ".trash-"
_SAVE_LOCK_FILE = ".save.lock"
# step-000001000, or step-000001000.2 for the 2nd replacement of the same step (see _unique_name).
_GENERATION_NAME = re.compile(r"^step-(\d+)(?:\.(\d+))?$")
_CONFIG_STAMP = re.compile(r"^# fdnet-run/\S+ save_id=([0-9a-f]+) step=(\d+)")


# ---------------------------------------------------------------------------- generations on disk


@dataclasses.dataclass(frozen=True)
class _Generation:
    path: Path
    step: int
    replacement: int  # 0 for step-N, k for step-N.k: later replacements of the same step sort newer

    @property
    def order(self) -> tuple[int, int]:
        return (self.step, self.replacement)


def _generations(checkpoints_dir: Path) -> list[_Generation]:
    """Published generation folders, newest first (by step, then by replacement)."""
    found = []
    try:
        entries = list(checkpoints_dir.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []
    for entry in entries:
        match = _GENERATION_NAME.match(entry.name)
        if match and entry.is_dir():
            found.append(_Generation(entry, int(match.group(1)), int(match.group(2) or 0)))
    return sorted(found, key=lambda g: g.order, reverse=True)


def read_weights_metadata(path: Path) -> dict[str, str]:
    """The metadata of a generation's weights file (step, save_id, modules, kind, checksums)."""
    # safe_open reads only the header, and refuses a file shorter than the header says (a torn
    # write), so this is a cheap completeness test as well as the metadata reader.
    with safe_open(str(path), framework="pt") as handle:
        return dict(handle.metadata() or {})


def _read_state(path: Path) -> dict:
    # mmap: the tensors are not read, only the structure; weights_only: no arbitrary code.
    payload = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    if not isinstance(payload, dict):
        raise ValueError(f"expected a dict, found {type(payload).__name__}")
    return payload


def _config_stamp(path: Path) -> tuple[str, int] | None:
    """(save_id, step) from config.yaml's first line, None when that line is not the stamp."""
    with open(path, encoding="utf-8") as handle:
        match = _CONFIG_STAMP.match(handle.readline())
    return (match.group(1), int(match.group(2))) if match else None


def _incomplete_reason(folder: Path) -> str | None:
    """Why ``folder`` is not a complete generation, or None when it is one."""
    try:
        metadata = read_weights_metadata(folder / WEIGHTS_FILE)
    except FileNotFoundError:
        return f"no {WEIGHTS_FILE}"
    except (SafetensorError, OSError) as exc:
        return f"{WEIGHTS_FILE} unreadable ({exc})"
    save_id = metadata.get("save_id")
    if not save_id:
        return f"{WEIGHTS_FILE} has no save_id"
    try:
        stamp = _config_stamp(folder / CONFIG_FILE)
    except FileNotFoundError:
        return f"no {CONFIG_FILE}"
    except (OSError, UnicodeDecodeError) as exc:
        return f"{CONFIG_FILE} unreadable ({exc})"
    if stamp is None or stamp[0] != save_id:
        return f"{CONFIG_FILE} belongs to another save than {WEIGHTS_FILE}"
    try:
        read_yaml_file(folder / CONFIG_FILE)
    except ConfigError as exc:  # says what is wrong (not YAML, an alias, too large)
        return f"{CONFIG_FILE} unreadable: {str(exc).removeprefix(str(folder / CONFIG_FILE) + ': ')}"
    except OSError as exc:
        return f"{CONFIG_FILE} unreadable ({exc.__class__.__name__})"
    if metadata.get("kind") == KIND_WEIGHTS:
        return None
    try:
        payload = _read_state(folder / STATE_FILE)
    except FileNotFoundError:
        return f"no {STATE_FILE}"
    except Exception as exc:  # torch raises several types for a torn or foreign file
        return f"{STATE_FILE} unreadable ({exc.__class__.__name__})"
    if payload.get("save_id") != save_id:
        return f"{STATE_FILE} belongs to another save than {WEIGHTS_FILE}"
    return None


def latest_checkpoint(run_dir: str | Path) -> Path:
    """Folder of the newest complete checkpoint of ``run_dir``.

    Generations ``run_dir/checkpoints/step-*`` are tried newest first; the first whose files are
    all readable and carry the same ``save_id`` is returned. A complete generation folder given
    directly (``RUN/checkpoints/step-...``) is returned as it is. Raises ConfigError naming
    ``run_dir`` when there is nothing complete to read.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: run directory not found")
    checkpoints_dir = run_dir / CHECKPOINTS_DIR
    rejected = []
    for generation in _generations(checkpoints_dir):
        reason = _incomplete_reason(generation.path)
        if reason is None:
            if rejected:  # an older checkpoint stands in for a damaged newer one: say so
                logging.getLogger(__name__).warning(
                    f"{run_dir}: skipped the newest checkpoint(s), damaged ({'; '.join(rejected[:3])}); using "
                    f"{generation.path.name}"
                )
            return generation.path
        rejected.append(f"{generation.path.name}: {reason}")
    if (run_dir / WEIGHTS_FILE).is_file():
        reason = _incomplete_reason(run_dir)
        if reason is None:
            return run_dir
        raise ConfigError(f"{run_dir}: not a complete checkpoint ({reason})")
    if checkpoints_dir.is_dir():
        detail = "; ".join(rejected[:3]) if rejected else "no step-* folder was ever published"
        raise ConfigError(f"{run_dir}: no complete checkpoint in {CHECKPOINTS_DIR}/ ({detail})")
    raise ConfigError(
        f"{run_dir}: not a run directory (no {CHECKPOINTS_DIR}/ or {WEIGHTS_FILE}; "
        "expected the --out folder of a training run)"
    )


def is_run(run_dir: str | Path) -> bool:
    """True when ``run_dir`` holds at least one complete checkpoint (or is one)."""
    try:
        latest_checkpoint(run_dir)
    except ConfigError:
        return False
    return True


def recorded_method(run_dir: str | Path) -> str | None:
    """The trained method a run directory records: ``method:`` in its config.yaml, which every
    method's run config has but FDNet's (the default method, whose config has no such key), so
    "fdnet" for a run without the key; None when ``run_dir`` holds no readable run."""
    from fdnet.config import read_yaml_file

    try:
        data = read_yaml_file(latest_checkpoint(run_dir) / CONFIG_FILE, "run config")
    except (OSError, ConfigError):
        return None
    if not isinstance(data, dict):
        return None
    method = data.get("method")
    return str(method) if method else "fdnet"


#: the folder in a run directory holding the best-validating weights (training with a validation pair)
BEST_DIR = "best"


def weights_folder(run_dir: str | Path) -> Path:
    """The folder whose weights a run directory means for inference: ``RUN/best`` when the run
    kept its best-validating weights there, else ``RUN`` itself (its newest checkpoint). A
    ``best/`` folder, or a generation folder (``RUN/checkpoints/step-...``), means itself."""
    run_dir = Path(run_dir)
    best = run_dir / BEST_DIR
    if (run_dir / CHECKPOINTS_DIR).is_dir() and best.is_dir() and is_run(best):
        return best
    return run_dir


def weights_note(given: str | Path, folder: Path, step) -> str | None:
    """What to tell the user when ``given`` (a run directory) was read from ``folder``
    (:func:`weights_folder`), else None."""
    if Path(folder) == Path(given):
        return None
    return (
        f"{given}: using its best-validating weights, {BEST_DIR}/ (step {step}); give "
        f"{Path(given) / CHECKPOINTS_DIR}/step-... for another checkpoint"
    )


def check_run_state(run_dir: str | Path, resume: bool) -> None:
    """What a training may do with ``run_dir``: ``--resume`` needs a complete checkpoint there,
    a fresh run needs a folder without one (never overwrite a run)."""
    if resume and not is_run(run_dir):
        raise ConfigError(f"{run_dir}: no run to resume (no complete checkpoint); drop --resume to start one")
    if not resume and is_run(run_dir):
        raise ConfigError(f"{run_dir}: already holds a run; use --resume to continue it or choose another --out")


# ---------------------------------------------------------------------------- saving


def _flatten_weights(modules: Mapping[str, torch.nn.Module]) -> dict[str, torch.Tensor]:
    tensors: dict[str, torch.Tensor] = {}
    for name, module in modules.items():
        if "." in name:
            raise ValueError(f"module name {name!r} must not contain '.'")
        for key, value in module.state_dict().items():
            # clone(): safetensors refuses tensors that share storage (tied weights, views).
            tensors[f"{name}.{key}"] = value.detach().to("cpu").contiguous().clone()
    return tensors


def _config_text(config: Any, save_id: str, step: int) -> str:
    data = to_dict(config) if dataclasses.is_dataclass(config) else to_dict(dict(config))
    # The stamp is a YAML comment, so load_yaml (which rejects unknown keys) still reads the file.
    return f"# fdnet-run/{FORMAT_VERSION} save_id={save_id} step={step}\n" + yaml.safe_dump(data, sort_keys=False)


def _write_synced(path: Path, data: bytes | memoryview) -> None:
    # Serialised in memory first and written here, so that a full disk is an OSError with its
    # errno (torch.save and safetensors report it as opaque RuntimeError / SafetensorError text).
    with open(path, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())


@contextlib.contextmanager
def _save_lock(checkpoints_dir: Path) -> Iterator[None]:
    """Serialise saves into one checkpoints/ folder (also across processes), so that the leftover
    ``.tmp-*`` folders removed at the start of a save can only be those of crashed saves."""
    if fcntl is None:
        yield
        return
    fd = os.open(str(checkpoints_dir / _SAVE_LOCK_FILE), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError as exc:
            # A filesystem without locks (some network mounts): the run's own RunLock already
            # keeps a second training out, so carry on without this extra guard.
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
                raise
        yield
    finally:
        os.close(fd)  # closing releases the flock


def _remove_folder(folder: Path, checkpoints_dir: Path, strict: bool = False) -> None:
    """Remove a generation: first renamed to a dot-folder (one atomic step, so no reader ever
    sees it half deleted), then deleted; a crash in between leaves a .trash-* that the next save
    removes. ``strict=False``: a folder that cannot be moved stays for the next save's pruning."""
    trash = checkpoints_dir / f"{_TRASH_PREFIX}{folder.name}-{uuid.uuid4().hex[:8]}"
    try:
        os.rename(folder, trash)
    except FileNotFoundError:
        return
    except OSError:
        if strict:
            raise
        return
    fsync_directory(checkpoints_dir)
    shutil.rmtree(trash, ignore_errors=True)


def _remove_leftovers(checkpoints_dir: Path) -> None:
    for entry in checkpoints_dir.iterdir():
        if entry.name.startswith((_TMP_PREFIX, _TRASH_PREFIX)):
            shutil.rmtree(entry, ignore_errors=True)


def _unique_name(checkpoints_dir: Path, step: int, existing: list[_Generation]) -> str:
    """``step-<step>``, or ``step-<step>.<k>`` sorting after every existing folder of that step
    (a same-step save is published beside the old one, which is removed only afterwards)."""
    replacement = max((g.replacement for g in existing if g.step == step), default=-1) + 1
    while True:
        name = f"step-{step:09d}" if replacement == 0 else f"step-{step:09d}.{replacement}"
        if not (checkpoints_dir / name).exists():
            return name
        replacement += 1


def _as_step(value: Any) -> int:
    try:
        step = operator.index(value)  # int, numpy integer, 0-d integer tensor
    except TypeError:
        step = None
    if step is None or isinstance(value, bool) or step < 0:
        raise ValueError(f"checkpoint step must be a non-negative integer, got {value!r}")
    return step


def _publish(
    run_dir: str | Path,
    modules: Mapping[str, torch.nn.Module],
    config: Any,
    optimizers: Mapping[str, torch.optim.Optimizer] | None,
    state: Mapping[str, Any] | None,
    step: int,
    kind: str,
    keep: int,
) -> Path:
    if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
        raise ValueError(f"keep must be a positive integer, got {keep!r}")
    # Everything that can fail for a programming reason happens before anything is written.
    save_id, files = _serialise(modules, config, optimizers, state, step, kind)
    checkpoints_dir = _make_checkpoints_dir(Path(run_dir))
    with _save_lock(checkpoints_dir):
        _remove_leftovers(checkpoints_dir)
        final = _write_generation(checkpoints_dir, files, step, save_id)
        _prune(checkpoints_dir, final, step, keep)
    return final


def _serialise(
    modules: Mapping[str, torch.nn.Module],
    config: Any,
    optimizers: Mapping[str, torch.optim.Optimizer] | None,
    state: Mapping[str, Any] | None,
    step: int,
    kind: str,
) -> tuple[str, dict[str, bytes | memoryview]]:
    """(save_id, file name -> its bytes) of one generation, every file in memory."""
    tensors = _flatten_weights(modules)
    save_id = uuid.uuid4().hex
    metadata = {
        "format": f"fdnet-run/{FORMAT_VERSION}",
        "kind": kind,
        "modules": ",".join(modules),
        "config_class": type(config).__name__,
        "save_id": save_id,
        "step": str(step),
        TENSORS_KEY: tensors_sha256(tensors),
    }
    files = {}
    if kind == KIND_TRAINING:
        buffer = io.BytesIO()
        torch.save(
            {
                "format": FORMAT_VERSION,
                "save_id": save_id,
                "step": step,
                "optimizers": {name: opt.state_dict() for name, opt in (optimizers or {}).items()},
                "state": dict(state or {}),
            },
            buffer,
        )
        files[STATE_FILE] = buffer.getbuffer()
        metadata[STATE_KEY] = bytes_sha256(files[STATE_FILE])
    files = {WEIGHTS_FILE: safetensors_bytes(tensors, metadata=metadata), **files}
    del tensors
    files[CONFIG_FILE] = _config_text(config, save_id, step).encode("utf-8")
    return save_id, files


def _make_checkpoints_dir(run_dir: Path) -> Path:
    """``run_dir/checkpoints/``, created (with ``run_dir``) when missing."""
    checkpoints_dir = run_dir / CHECKPOINTS_DIR
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        if not checkpoints_dir.is_dir():
            checkpoints_dir.mkdir()
            fsync_directory(run_dir)
    except OSError as exc:
        raise output_error(
            f"{checkpoints_dir}: cannot create the checkpoint folder ({exc.strerror or exc})", exc
        ) from exc
    return checkpoints_dir


def _write_generation(checkpoints_dir: Path, files: Mapping[str, bytes | memoryview], step: int, save_id: str) -> Path:
    """Write ``files`` into a ``.tmp-*`` folder, read them back and publish the folder by one
    rename; returns the published folder. Called under the save lock."""
    tmp = checkpoints_dir / f"{_TMP_PREFIX}{step}-{save_id}"
    try:
        tmp.mkdir()
        for name, data in files.items():
            _write_synced(tmp / name, data)
        fsync_directory(tmp)
        # Read the unit back before it may become current: a state that weights_only=True
        # cannot load (e.g. a numpy array) would otherwise only show up at --resume.
        reason = _incomplete_reason(tmp)
        if reason is not None:
            raise ValueError(
                f"{tmp}: the checkpoint for step {step} cannot be read back ({reason}); a training "
                "state may hold only tensors, numbers, strings, lists and dicts"
            )

        existing = _generations(checkpoints_dir)
        # Generations of a later step belong to a history the caller has abandoned (it resumed
        # from an earlier checkpoint, or best/ is being re-chosen after such a resume). They
        # would shadow the new one as "newest", so they go before the publishing rename; a
        # crash in between leaves the earlier generation the caller resumed from as current.
        for generation in existing:
            if generation.step > step:
                _remove_folder(generation.path, checkpoints_dir, strict=True)
        final = checkpoints_dir / _unique_name(checkpoints_dir, step, existing)
        os.rename(tmp, final)  # the one step that makes the new generation current
        fsync_directory(checkpoints_dir)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        current = next((g.path.name for g in _generations(checkpoints_dir) if _incomplete_reason(g.path) is None), None)
        reason = "no space left on the device" if exc.errno == errno.ENOSPC else (exc.strerror or str(exc))
        still = f"{current} is still the current checkpoint" if current else "no earlier checkpoint exists"
        raise output_error(
            f"{checkpoints_dir}: cannot save the checkpoint for step {step} ({reason}); {still}", exc
        ) from exc
    except BaseException:  # incl. Ctrl-C: never leave our partial folder behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def _prune(checkpoints_dir: Path, final: Path, step: int, keep: int) -> None:
    """Keep the new generation ``final`` plus the keep-1 newest complete older ones (an incomplete
    one is never worth keeping, and never counts); older folders of the same step are replaced,
    not kept. Called only once ``final`` is published, so a crash never leaves fewer."""
    kept = 1
    for generation in _generations(checkpoints_dir):
        if generation.path == final:
            continue
        if generation.step != step and kept < keep and _incomplete_reason(generation.path) is None:
            kept += 1
            continue
        _remove_folder(generation.path, checkpoints_dir)


def save_checkpoint(
    run_dir: str | Path,
    modules: Mapping[str, torch.nn.Module],
    config: Any,
    optimizers: Mapping[str, torch.optim.Optimizer] | None = None,
    state: Mapping[str, Any] | None = None,
    keep: int = 2,
) -> Path:
    """Publish one resumable checkpoint (weights + training state + config) as one unit.

    Written completely into ``run_dir/checkpoints/.tmp-<step>-<id>/``, every file fsynced and read
    back, then made current by one rename to ``run_dir/checkpoints/step-<step:09d>/`` (parent
    fsynced). The previous complete checkpoint stays until then; older ones beyond ``keep`` are
    pruned only afterwards; leftovers of crashed saves are removed first. ``state`` holds plain
    tensors, numbers, strings, lists and dicts (read back with ``torch.load(weights_only=True)``);
    ``state["step"]`` is the generation's step (0 if absent). Saving a step again replaces the
    old folder safely (the new one is published under a unique name, then the old one removed);
    generations of later steps than this one (an abandoned history) are removed.
    ``config`` is a dataclass or a plain dict. Returns the published folder.

    A write error (e.g. a full disk) raises OutputError (a ConfigError and an OSError with the
    errno) naming the folder, with the previous checkpoint left current and no partial folder
    that a reader would take.
    """
    step = _as_step((state or {}).get("step", 0))
    return _publish(run_dir, modules, config, optimizers, state, step, KIND_TRAINING, keep)


def save_weights(
    run_dir: str | Path, modules: Mapping[str, torch.nn.Module], config: Any, step: int = 0, keep: int = 1
) -> Path:
    """Publish an inference-only checkpoint (weights + config, no optimiser state) as one unit,
    the same way as :func:`save_checkpoint`; for ``best/`` and exports. ``step`` is recorded in
    the weights' metadata (which step the weights are from)."""
    return _publish(run_dir, modules, config, None, None, _as_step(step), KIND_WEIGHTS, keep)
