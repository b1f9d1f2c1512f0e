"""Synthetic appearance conditions (fdnet.data.appearance) and their use by FDNet's training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fdnet.cli import main
from fdnet.config import replace_dotted
from fdnet.data import appearance
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import preset, validate
from fdnet.methods.fdnet.training import load_training_images
from fdnet.training.data import TrainingImages
from tests.training.test_loop import make_dataset


def _images(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    # mid-grey images with texture, so darkening and brightening both have room
    return (torch.rand((n, 3, 12, 20), generator=g) * 120 + 60).to(torch.uint8)


def _data():
    return TrainingImages(["day", "dusk"], [_images(seed=1), _images(seed=2)], [np.arange(6), np.arange(10, 16)])


def test_each_real_condition_gets_one_condition_per_change_in_order():
    data = _data()
    out = appearance.with_synthetic_conditions(data, ["night", "cast"], seed=3)
    assert out.names == ["day", "dusk", "day~night", "day~cast", "dusk~night", "dusk~cast"]
    assert all(x.dtype == torch.uint8 and x.shape == (6, 3, 12, 20) for x in out.images)
    assert torch.equal(out.images[0], data.images[0]) and torch.equal(out.images[1], data.images[1])
    assert np.array_equal(out.frame_ids[4], data.frame_ids[1])
    # the input is not changed in place
    assert data.names == ["day", "dusk"] and len(data.images) == 2


def test_the_same_seed_rebuilds_the_same_conditions_and_another_seed_does_not():
    a = appearance.with_synthetic_conditions(_data(), ["night", "contrast"], seed=5)
    b = appearance.with_synthetic_conditions(_data(), ["night", "contrast"], seed=5)
    c = appearance.with_synthetic_conditions(_data(), ["night", "contrast"], seed=6)
    assert all(torch.equal(x, y) for x, y in zip(a.images, b.images))
    assert not torch.equal(a.images[2], c.images[2])


def test_what_each_change_does():
    images = _images(n=32)
    g = torch.Generator().manual_seed(0)
    mean = images.float().mean()
    night = appearance.changed(images, "night", g).float()
    snow = appearance.changed(images, "snow", g).float()
    assert night.mean() < 0.6 * mean, "night darkens"
    assert snow.mean() > mean and snow.std() < images.float().std(), "snow brightens and flattens"
    cast = appearance.changed(images, "cast", g).float()
    ratios = cast.mean(dim=(2, 3)) / images.float().mean(dim=(2, 3))
    assert (ratios.max(dim=1).values - ratios.min(dim=1).values).mean() > 0.1, "cast scales the channels apart"
    # each image its own strength: the darkening differs between images
    per_image = night.mean(dim=(1, 2, 3)) / images.float().mean(dim=(1, 2, 3))
    assert per_image.std() > 0.02


def test_no_change_returns_the_data_and_unknown_or_repeated_changes_are_config_errors():
    data = _data()
    assert appearance.with_synthetic_conditions(data, [], seed=0) is data
    with pytest.raises(ConfigError, match="unknown change.*'fog'.*night, snow, cast, contrast"):
        appearance.with_synthetic_conditions(data, ["fog"], seed=0)
    with pytest.raises(ConfigError, match="twice"):
        validate(replace_dotted(preset("tiny"), {"data.synthetic_conditions": ["night", "night"]}))


def test_fdnet_trains_on_the_added_conditions_and_resumes(tmp_path, capsys):
    data = make_dataset(tmp_path / "data")
    config = replace_dotted(preset("tiny"), {"data.root": str(data), "data.synthetic_conditions": ["night"]})
    assert load_training_images(config).names == ["summer", "winter", "summer~night", "winter~night"]
    out = tmp_path / "run"
    common = [
        "train",
        "--data",
        str(data),
        "--preset",
        "tiny",
        "--no-progress",
        "--out",
        str(out),
        "--set",
        "data.synthetic_conditions=night",
    ]
    assert main([*common, "--max-minutes", "0"]) == 0  # stops after its first step
    assert "summer~night, winter~night" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--out", str(out), "--resume", "--no-progress"]) == 0
    assert "finished at step 8/8" in capsys.readouterr().out


def test_an_unknown_change_on_the_command_line_is_a_clear_error(tmp_path, capsys):
    data = make_dataset(tmp_path / "data")
    assert (
        main(
            [
                "train",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "run"),
                "--set",
                "data.synthetic_conditions=fog",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "fdnet train: error:" in err and "'fog'" in err
