"""What a method that learns from images learns from: a dataset folder (--fit), its frames."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from fdnet.descriptors.fitting import check_fit_frames, fit_image_paths
from fdnet.errors import ConfigError, DataError


def _images(folder, n):
    folder.mkdir(parents=True)
    for i in range(n):
        Image.fromarray(np.full((4, 4, 3), 10 * i, np.uint8)).save(folder / f"{i:03d}.png")


def test_every_condition_and_the_frames_of_each(tmp_path):
    _images(tmp_path / "data" / "summer", 6)
    _images(tmp_path / "data" / "winter", 6)
    paths, description = fit_image_paths(tmp_path / "data")
    assert len(paths) == 12
    paths, description = fit_image_paths(tmp_path / "data", "1:4")
    assert [p.parent.name + "/" + p.name for p in paths] == [
        f"{c}/{i:03d}.png" for c in ("summer", "winter") for i in (1, 2, 3)
    ]
    assert "frames 1:4: 6 images of summer (3), winter (3)" in description
    assert str((tmp_path / "data").resolve()) in description


def test_a_plain_folder_of_images(tmp_path):
    _images(tmp_path / "flat", 5)
    paths, description = fit_image_paths(tmp_path / "flat", ":2")
    assert len(paths) == 2 and "2 images of flat (2)" in description


def test_nothing_to_fit_on(tmp_path):
    (tmp_path / "empty" / "summer").mkdir(parents=True)
    with pytest.raises(DataError, match="empty: no images to fit on"):
        fit_image_paths(tmp_path / "empty", where="--fit")
    with pytest.raises(DataError, match="folder not found"):
        fit_image_paths(tmp_path / "missing")
    _images(tmp_path / "data" / "summer", 3)
    with pytest.raises(DataError, match="frames 10:20: no images to fit on"):
        fit_image_paths(tmp_path / "data", "10:20")


def test_fit_frames_must_be_text():
    assert check_fit_frames("0:1576", "x") == "0:1576" and check_fit_frames(None, "x") is None
    with pytest.raises(ConfigError, match="not START:END text"):
        check_fit_frames(94560, "trunk-whitened")  # what YAML makes of 0:1576 (base 60)
    with pytest.raises(DataError, match="END must be greater"):
        check_fit_frames("5:2", "x")
