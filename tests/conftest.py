"""Shared test fixtures.

Tests that need the real data in ``../shared/data`` use the ``shared_data`` fixture (or
``require_shared``), which skips with a clear reason when the folder is absent, so a fresh clone
elsewhere still passes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FDNET_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


def require_shared(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with a clear reason if it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not available: {path} is absent (set FDNET_SHARED_DATA to its folder)")
    return path


@pytest.fixture
def shared_data() -> Path:
    return require_shared()


@pytest.fixture(autouse=True)
def _few_threads():
    # CI has 2 cores; keep torch (when a test uses it) from oversubscribing them.
    try:
        import torch
    except ImportError:  # pragma: no cover
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(min(2, previous))
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
