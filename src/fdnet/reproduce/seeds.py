"""Repeated training (``fdnet reproduce --seeds N``): the seeds and run folders of a variant trained
N times, and each number's mean and spread over those runs.

A variant trained with seeds S, S+1, ..., S+N-1 (S the run config's own ``runtime.seed``) keeps its
first run in a single run's folder, so a run trained there with ``--seeds 1`` is reused (or resumed)
as the first seed's, and seed S+k trains into ``<folder>-seed<S+k>``.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Sequence


def seeds_from(first: int, count: int) -> list[int]:
    """``count`` consecutive seeds from ``first``."""
    return [first + k for k in range(count)]


def seed_folder(folder: Path, first: int, seed: int) -> Path:
    """Where the run with ``seed`` trains: ``folder`` for the first seed, else ``folder-seed<SEED>``."""
    folder = Path(folder)
    return folder if seed == first else folder.with_name(f"{folder.name}-seed{seed}")


def spread(values: Sequence[float | None]) -> dict:
    """The mean and spread of one number over N runs: ``n`` (runs with a number), ``mean``,
    ``std`` (the sample standard deviation, None with fewer than two numbers), ``min``, ``max``.
    A run without the number (None, or not finite) is left out and counted in ``missing``."""
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return {
        "n": len(finite),
        "mean": statistics.fmean(finite) if finite else None,
        "std": statistics.stdev(finite) if len(finite) > 1 else None,
        "min": min(finite) if finite else None,
        "max": max(finite) if finite else None,
        "missing": len(values) - len(finite),
    }


def spread_text(summary: dict, digits: int = 3) -> str:
    """A table cell: ``mean ± std (min–max)``; "-" when no run has the number."""
    if summary.get("mean") is None:
        return "-"
    text = f"{summary['mean']:.{digits}f}"
    if summary.get("std") is not None:
        text += f" \u00b1 {summary['std']:.{digits}f} ({summary['min']:.{digits}f}\u2013{summary['max']:.{digits}f})"
    if summary.get("missing"):
        text += f" [{summary['missing']} run(s) without]"
    return text
