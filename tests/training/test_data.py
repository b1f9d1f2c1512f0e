"""Training data: the validation pair's images and ground truth (fdnet.training.data)."""

import pytest

from fdnet.errors import DataError
from fdnet.methods.settings import ValidationConfig
from fdnet.training.data import load_validation_images
from tests.training.test_loop import make_dataset


def test_validation_frames_give_the_pair_and_its_ground_truth(tmp_path):
    root = make_dataset(tmp_path / "data", n=10)
    pair = load_validation_images(root, ValidationConfig("summer", "winter", "2:8", 1), (16, 32))
    assert pair.reference.shape[0] == pair.query.shape[0] == 6
    assert pair.ground_truth.has_match.all()
    assert load_validation_images(root, ValidationConfig(), (16, 32)) is None


def test_validation_frames_outside_the_folders_name_the_range_not_a_missing_match(tmp_path):
    root = make_dataset(tmp_path / "data", n=10)
    with pytest.raises(
        DataError, match=r"validation winter->summer: frame range 50:60 selects no images of " r".*summer \(10 images\)"
    ):
        load_validation_images(root, ValidationConfig("summer", "winter", "50:60", 0), (16, 32))
