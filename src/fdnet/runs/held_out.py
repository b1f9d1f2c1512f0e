"""Held-out frames: a trained model is measured on images it did not learn from.

A run's config records what it trained on (``data.root``, ``data.conditions``, ``data.frames``,
``data.dataset_format``, ``data.split``). :func:`check_held_out` compares that with what a
command is about to evaluate or calibrate on and refuses an overlap, naming both ranges: a
model scoring its own training images (Gardens Point 0:100 after training on 0:100 gave R@1
1.000) measures memory, not place recognition. ``evaluate``, ``calibrate`` and ``loop-closure``
call it for every trained method (``--allow-training-frames`` measures it on purpose).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from fdnet.errors import ConfigError


def training_data(run_dir: str | Path) -> dict | None:
    """The ``data`` section of the run's newest config (None when it records none)."""
    from fdnet.config import read_yaml_file
    from fdnet.runs.checkpoints import CONFIG_FILE, latest_checkpoint

    try:
        config = read_yaml_file(latest_checkpoint(run_dir) / CONFIG_FILE, "run config")
    except (OSError, ConfigError):
        return None
    data = config.get("data") if isinstance(config, dict) else None
    return data if isinstance(data, dict) and data.get("root") else None


def _same_folder(a, b) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def check_held_out(
    method: str,
    run_dir: str | Path,
    data: str | Path,
    conditions: Sequence[str],
    frames: str | None = None,
    dataset_format: str | None = None,
    split: str | None = None,
    allow: bool = False,
) -> None:
    """Refuse (ConfigError) to evaluate ``method`` from ``run_dir`` on frames of ``data`` it was
    trained on: the same folder, a shared condition, overlapping frame ranges (with a dataset
    format: the same format and split). ``allow`` lets it through."""
    trained = training_data(run_dir)
    if allow or trained is None or not _same_folder(trained["root"], data):
        return
    shared = sorted(set(conditions) & set(trained.get("conditions") or conditions))
    if not shared:
        return
    if (trained.get("dataset_format") or None) != (dataset_format or None):
        return
    if dataset_format:
        if (trained.get("split") or None) != (split or None):
            return
        what = f"split {split or 'all'}"
    else:
        from fdnet.data.dataset import frame_ranges_overlap

        if not frame_ranges_overlap(trained.get("frames"), frames):
            return
        what = f"frames {frames or 'all'}"
    raise ConfigError(
        f"{method} ({run_dir}) was trained on frames {trained.get('frames') or 'all'} of {data} "
        f"({', '.join(shared)}); {what} overlap them: the numbers would measure what the model has "
        "seen, not recognition of new places. Give held-out --frames, or --allow-training-frames to "
        "measure it anyway"
    )
