"""The record of settings changed when a run is resumed with ``--override``
(``RUN_DIR/changes.yaml``), so the run's history stays true."""

from __future__ import annotations

from pathlib import Path

import yaml

from fdnet.config import read_yaml_file
from fdnet.errors import ConfigError
from fdnet.io import atomic_write_text
from fdnet.runs.lock import local_time_stamp  # the same local time stamp as the lock's holder details

CHANGES_FILE = "changes.yaml"


def read_changes(run_dir: str | Path) -> list[dict]:
    """Entries of ``run_dir/changes.yaml`` (``step``, ``time``, ``command``, ``changes``), oldest
    first; [] when the run was never resumed with other settings."""
    path = Path(run_dir) / CHANGES_FILE
    try:
        data = read_yaml_file(path, "record of changed settings")
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the record of changed settings ({exc})") from exc
    if data is None:
        return []
    if not isinstance(data, list) or not all(isinstance(e, dict) for e in data):
        raise ConfigError(f"{path}: expected a list of entries (step, time, command, changes)")
    return data


def record_changes(run_dir: str | Path, step: int, differences: list[str], command: str = "") -> None:
    """Append to ``run_dir/changes.yaml`` (rewritten atomically) that the settings in
    ``differences`` (as from :func:`fdnet.runs.loading.config_differences`) changed at ``step``, when a run is
    resumed with ``--override``; the run's history stays true. Nothing is written for no change."""
    if not differences:
        return
    entries = read_changes(run_dir)
    entries.append({"step": int(step), "time": local_time_stamp(), "command": command, "changes": list(differences)})
    atomic_write_text(Path(run_dir) / CHANGES_FILE, yaml.safe_dump(entries, sort_keys=False))
