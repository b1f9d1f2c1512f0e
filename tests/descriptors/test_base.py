"""Descriptor.fingerprint: what makes the vectors, not where the weights were read from."""

import numpy as np
import pytest

from fdnet.descriptors.base import Descriptor


class _Stored(Descriptor):
    name = "stored"

    def __init__(self, checkpoint: str, weights: np.ndarray, size: int = 8):
        self.checkpoint = checkpoint
        self.matrix = weights
        self.size = size

    @property
    def dim(self) -> int:
        return int(self.matrix.shape[1])

    def describe(self, images):  # pragma: no cover - not called
        raise NotImplementedError

    def settings(self) -> dict:
        return {"checkpoint": self.checkpoint, "size": self.size}


def test_fingerprint_ignores_how_the_run_directory_is_spelled(tmp_path):
    weights = np.arange(6, dtype=np.float32).reshape(2, 3)
    relative = _Stored("run1", weights)
    absolute = _Stored(str(tmp_path / "run1"), weights.copy())
    moved = _Stored(str(tmp_path / "elsewhere" / "run1"), weights.copy())
    assert relative.fingerprint() == absolute.fingerprint() == moved.fingerprint()


def test_fingerprint_still_tells_weights_and_settings_apart():
    weights = np.arange(6, dtype=np.float32).reshape(2, 3)
    base = _Stored("run1", weights).fingerprint()
    assert _Stored("run1", weights + 1).fingerprint() != base
    assert _Stored("run1", weights, size=16).fingerprint() != base


def test_a_vocabulary_fitted_from_the_same_folder_spelled_two_ways_has_one_fingerprint(tmp_path, monkeypatch):
    from PIL import Image

    from fdnet.descriptors import create

    rng = np.random.default_rng(0)
    folder = tmp_path / "route" / "day"
    folder.mkdir(parents=True)
    for i in range(4):
        Image.fromarray(rng.integers(0, 256, size=(96, 128, 3)).astype(np.uint8)).save(folder / f"{i}.png")
    monkeypatch.chdir(tmp_path)
    relative = create("dbow", fit="route/day", depth=2, branching=4)
    absolute = create("dbow", fit=str(folder), depth=2, branching=4)
    assert relative.fingerprint() == absolute.fingerprint()


def test_describing_appearance_is_declared_on_the_base_class():
    """Whether a method describes appearance is a declared capability: the methods that override
    describe_appearance say so, and the others refuse to, naming themselves."""
    from fdnet.descriptors.base import Descriptor
    from fdnet.descriptors.registry import all_specs

    for spec in all_specs():
        cls = spec.descriptor_class()
        overrides = cls.describe_appearance is not Descriptor.describe_appearance
        assert cls.describes_appearance == overrides, spec.name
    assert [s.name for s in all_specs() if s.descriptor_class().describes_appearance] == ["fdnet"]
    from fdnet.descriptors import create

    with pytest.raises(NotImplementedError, match="raw describes no appearance"):
        create("raw").describe_both(np.zeros((1, 32, 64, 3), np.float32))
