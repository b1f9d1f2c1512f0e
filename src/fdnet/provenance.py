"""Where a result came from: the one record every JSON fdnet writes carries as ``provenance``.

:func:`provenance` gives the fdnet version and, when the package runs from a git checkout, its
commit (and whether the tree had uncommitted changes); the Python, torch, numpy and faiss
versions; the device the work ran on and the machine's CPU model and core count; the seeds; and
the command line. Versions are read from the installed distributions' metadata, so nothing
heavy is imported to record them.
"""

from __future__ import annotations

import datetime
import functools
import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any, Mapping

#: distributions whose versions are recorded: key -> distribution names tried in order
LIBRARIES = {"torch": ("torch",), "numpy": ("numpy",), "faiss": ("faiss-cpu", "faiss-gpu", "faiss")}


def _version(names) -> str | None:
    for name in names:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return None


@functools.lru_cache(maxsize=1)
def git_commit() -> dict | None:
    """``{"commit": SHA, "dirty": bool}`` of the checkout this package's source lies in (read once per
    process: the code running is the code imported), or None
    when it is not in one (an installed wheel) or git is not there."""
    source = Path(__file__).resolve().parent
    try:
        top = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "--show-toplevel"], capture_output=True, text=True, timeout=10
        )
        if top.returncode != 0 or not (source.is_relative_to(Path(top.stdout.strip()).resolve())):
            return None
        commit = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10
        )
        status = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if commit.returncode != 0:
        return None
    return {"commit": commit.stdout.strip(), "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None}


@functools.lru_cache(maxsize=1)
def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else :func:`platform.processor`)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, sep, value = line.partition(":")
                if sep and key.strip() in ("model name", "Model", "Hardware", "cpu model"):
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def device_description(device: str | None = None) -> str:
    """What ``device`` is: a GPU's name for a CUDA device (when torch is already imported), else
    the device string; without one, ``cpu`` unless torch sees a GPU."""
    torch = sys.modules.get("torch")
    spec = None if device in (None, "auto") else str(device)
    if torch is None:
        return spec or "cpu"
    try:
        if (spec is None or spec.startswith("cuda")) and torch.cuda.is_available():
            index = int(spec.partition(":")[2] or 0) if spec else 0
            return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    except Exception:  # noqa: BLE001 (a description only: a driver's error must not stop the record)
        pass
    return spec or "cpu"


def provenance(command: str | None = None, seeds: Mapping[str, Any] | Any = None, device: str | None = None) -> dict:
    """The record: ``fdnet_version``, ``git`` (commit and dirty, or None), ``python``,
    ``libraries`` (torch, numpy, faiss versions), ``device``, ``cpu`` (model), ``cpu_count``,
    ``platform``, ``seeds`` (as given; None when the work draws no random numbers), ``command``
    (default: this process's command line) and ``created`` (local time, ISO 8601)."""
    from fdnet.version import __version__

    if command is None:
        command = shlex.join([Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]])
    return {
        "fdnet_version": __version__,
        "git": git_commit(),
        "python": platform.python_version(),
        "libraries": {key: _version(names) for key, names in LIBRARIES.items()},
        "device": device_description(device),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "seeds": seeds,
        "command": command,
        "created": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
    }
