"""Format registry: detection, naming, settings from strings, unknown names."""

import pytest

from fdnet.data.formats import describe_formats, detect_format, format_names, get_format, open_split
from fdnet.errors import ConfigError, DataError

from .conftest import write_frames


def test_every_format_is_described():
    described = describe_formats()
    assert (
        set(described)
        == set(format_names())
        == {
            "vprbench",
            "vpr_tutorial",
            "vg_benchmark",
            "oxford_robotcar",
            "alderley",
            "fas",
            "st_lucia",
            "nordland",
            "folders",
        }
    )
    assert described["nordland"]["defaults"]["tolerance"] == 5
    assert described["alderley"]["defaults"]["tolerance"] == 2
    assert described["fas"]["defaults"]["tolerance"] == 3
    assert described["oxford_robotcar"]["defaults"]["tolerance_m"] == 30.0
    assert described["st_lucia"]["defaults"]["tolerance_m"] == 30.0
    assert get_format("robotcar").name == "oxford_robotcar"


def test_unknown_format_and_empty_folder(tmp_path):
    with pytest.raises(ConfigError, match="unknown dataset format 'kitti'; available: vprbench"):
        get_format("kitti")
    with pytest.raises(DataError, match="not a dataset layout fdnet recognises"):
        detect_format(tmp_path)
    with pytest.raises(DataError, match="dataset folder not found"):
        open_split(tmp_path / "nope")


def test_settings_given_as_strings_are_converted(tmp_path):
    for c in ("a", "b"):
        write_frames(tmp_path / c, [f"{i}.png" for i in range(4)])
    split = open_split(tmp_path, tolerance="1")
    assert split.ground_truth.positives[0].tolist() == [0, 1]
    with pytest.raises(ConfigError, match="tolerance: expected int"):
        open_split(tmp_path, tolerance="wide")


def test_override_detected_format(tmp_path):
    for c in ("summer", "winter"):
        write_frames(tmp_path / c, [f"images-{i:05d}.png" for i in range(10, 50, 10)])
    assert detect_format(tmp_path) == "nordland"
    plain = open_split(tmp_path, dataset_format="folders")
    assert plain.query.frame_ids.tolist() == [0, 1, 2, 3]  # positions, not file numbers
