"""Half-width crops at a given overlap: the right columns, written once, rewritten when the
images change."""

from __future__ import annotations

import numpy as np
from PIL import Image

from fdnet.data.dataset import Traverse
from fdnet.data.images import load_image
from fdnet.reproduce.viewpoint import crop_columns, write_crops


def test_crop_columns_overlap_the_left_half():
    assert crop_columns(100, 1.0) == (0, 50)
    assert crop_columns(100, 0.9) == (5, 55)
    assert crop_columns(100, 0.75) == (12, 62)  # 12.5 rounds to even
    assert crop_columns(101, 0.65) == (18, 68)


def test_crops_hold_the_shifted_columns_and_are_written_once(tmp_path):
    # each column's grey level is its index, so a crop's first column says where it starts
    columns = np.tile(np.arange(100, dtype=np.uint8), (8, 1))
    paths = []
    for i in range(2):
        paths.append(tmp_path / f"frame_{i}.png")
        Image.fromarray(columns).save(paths[-1])
    traverse = Traverse("summer", paths)
    crops = write_crops(traverse, 0.9, tmp_path / "crops")
    assert len(crops) == 2
    first = load_image(crops[0])
    assert first.shape == (8, 50, 3)
    assert round(first[0, 0, 0] * 255) == 5 and round(first[0, -1, 0] * 255) == 54
    written = crops[0].stat().st_mtime_ns
    assert write_crops(traverse, 0.9, tmp_path / "crops") == crops
    assert crops[0].stat().st_mtime_ns == written
    Image.fromarray(255 - columns).save(paths[0])  # the source changed: crops are made again
    again = write_crops(traverse, 0.9, tmp_path / "crops")
    assert round(load_image(again[0])[0, 0, 0] * 255) == 250
