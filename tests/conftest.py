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


def write_day_night_route(root: Path, places: int) -> Path:
    """``root/route/{day,night}/NNN.png``: ``places`` random 32x64 images, the night copy of each
    darker (x0.6) with a little noise; frame i is the same place in both conditions."""
    from PIL import Image

    rng = np.random.default_rng(0)
    images = rng.random((places, 32, 64, 3))
    for k, condition in enumerate(("day", "night")):
        (root / "route" / condition).mkdir(parents=True)
        for i, place in enumerate(images):
            image = np.clip(place * (1.0 - 0.4 * k) + 0.05 * rng.random(place.shape), 0, 1)
            Image.fromarray((image * 255).astype(np.uint8)).save(root / "route" / condition / f"{i:03d}.png")
    return root / "route"
