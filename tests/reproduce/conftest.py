"""Stand-in methods and a small route for the runner's tests (no model, milliseconds per run).

``Pixels`` and ``FittedPixels`` count their calls in ``CALLS`` so a test can say exactly what a run
described and fitted; ``factory`` builds them by name as ``fdnet.descriptors.create`` would.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
from PIL import Image

from fdnet.descriptors import registry
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import NotAvailableError
from fdnet.reproduce import ReproduceSettings

CALLS: Counter = Counter()


@dataclass(frozen=True)
class PixelsSettings(MethodSettings):
    method: ClassVar[str] = "pixels"
    #: side of the square grey thumbnail
    size: int = 8

    def check(self) -> None:
        self.need_whole("size", minimum=1)


class Pixels(Descriptor):
    """Mean-centred 8x8 grey pixels, cosine. ``interrupt_after``: raise KeyboardInterrupt on that
    describe call (a user's Ctrl-C in the middle of a run)."""

    name = "pixels"
    interrupt_after: int | None = None

    Settings: ClassVar[type] = PixelsSettings

    def __init__(self, settings: PixelsSettings | None = None, **options):
        self.conf = PixelsSettings.build(settings, options)
        self.input_size = (int(self.conf.size), int(self.conf.size))

    @property
    def dim(self) -> int:
        return self.input_size[0] * self.input_size[1]

    def describe(self, images):
        CALLS[f"{self.name}.describe"] += 1
        if self.interrupt_after is not None and CALLS[f"{self.name}.describe"] >= self.interrupt_after:
            raise KeyboardInterrupt
        grey = images.mean(axis=3).reshape(len(images), -1)
        return l2_normalize(grey - grey.mean(axis=1, keepdims=True))


class FittedPixels(Pixels):
    """Pixels minus the mean reference image: a method that learns from the map (like DBoW)."""

    name = "fitted"
    #: what ``min_fit_images`` says (a test raises it above the route's frame count)
    fewest: int = 1

    def __init__(self, settings: PixelsSettings | None = None, **options):
        super().__init__(settings, **options)
        self.mean = None

    @property
    def needs_fit(self) -> bool:
        return self.mean is None

    @property
    def min_fit_images(self) -> int:
        return self.fewest

    def fit(self, paths):
        from fdnet.data.images import load_images

        CALLS["fitted.fit"] += 1
        self.mean = load_images(list(paths), self.input_size).mean(axis=(0, 3)).reshape(-1)

    def describe(self, images):
        CALLS["fitted.describe"] += 1
        grey = images.mean(axis=3).reshape(len(images), -1)
        return l2_normalize(grey - self.mean)


def factory(name: str, **options):
    if name == "pixels":
        return Pixels(**options)
    if name == "fitted":
        return FittedPixels(**options)
    raise NotAvailableError(f"{name}: not available in this test")


@pytest.fixture(autouse=True)
def _stand_ins(monkeypatch):
    # registered so the runner's check of method names knows them; built by ``factory``
    monkeypatch.setitem(
        registry._METHODS, "pixels", registry.MethodSpec("pixels", "test stand-in", f"{__name__}:Pixels")
    )
    monkeypatch.setitem(
        registry._METHODS,
        "fitted",
        registry.MethodSpec("fitted", "test stand-in", f"{__name__}:FittedPixels", fit=True),
    )
    CALLS.clear()
    Pixels.interrupt_after = None
    yield


@pytest.fixture
def route(tmp_path):
    """Three conditions of 10 aligned 24x32 frames: a random scene, dimmed and noisier per condition."""
    rng = np.random.default_rng(0)
    root = tmp_path / "route"
    scenes = rng.random((10, 24, 32))
    for condition, gain in (("day", 1.0), ("dusk", 0.6), ("night", 0.3)):
        (root / condition).mkdir(parents=True)
        for i, scene in enumerate(scenes):
            pixels = np.clip(gain * scene + 0.05 * rng.standard_normal(scene.shape), 0, 1)
            Image.fromarray((pixels * 255).astype(np.uint8)).save(root / condition / f"frame_{i:03d}.png")
    return root


def settings(route, out, **changes) -> ReproduceSettings:
    base = dict(
        data=route,
        out=out,
        methods=["pixels"],
        experiments=["comparison"],
        batch_size=64,
        command="fdnet reproduce (test)",
    )
    base.update(changes)
    return ReproduceSettings(**base)
