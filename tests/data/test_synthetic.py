"""The synthetic route generator and `fdnet synth`."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.cli import main
from fdnet.data.groundtruth import GroundTruth
from fdnet.data.synthetic import CONDITIONS, generate_route, make_scene, render_route
from fdnet.descriptors.classic import RawThumbnail, SeqSLAMFrontEnd
from fdnet.errors import ConfigError, DataError
from fdnet.matching.similarity import top_k


def test_render_shapes_range_and_determinism():
    a = render_route(frames=6, seed=3, size=(32, 64))
    assert list(a) == list(CONDITIONS)
    for images in a.values():
        assert images.shape == (6, 32, 64, 3) and images.dtype == np.float32
        assert images.min() >= 0.0 and images.max() <= 1.0
    b = render_route(frames=6, seed=3, size=(32, 64))
    for c in CONDITIONS:
        np.testing.assert_array_equal(a[c], b[c])
    other = render_route(frames=6, seed=4, size=(32, 64), conditions=("summer",))
    assert np.abs(other["summer"] - a["summer"]).mean() > 0.02


def test_condition_alone_renders_as_in_the_full_set():
    """A condition's randomness is its own: asking for fewer conditions changes nothing."""
    full = render_route(frames=4, seed=1, size=(32, 64))
    night = render_route(frames=4, seed=1, size=(32, 64), conditions=("night",))
    np.testing.assert_array_equal(full["night"], night["night"])


def test_places_do_not_depend_on_route_length():
    short, long = make_scene(10.0, seed=5), make_scene(40.0, seed=5)
    assert [b.x0 for b in short.buildings] == [b.x0 for b in long.buildings[: len(short.buildings)]]
    assert short.dashes == long.dashes[: len(short.dashes)]


def test_conditions_differ_a_lot_in_pixels_but_night_is_dark():
    r = render_route(frames=10, seed=0, size=(32, 64))
    summer, night, winter = r["summer"], r["night"], r["winter"]
    assert np.abs(summer - winter).mean() > 0.1
    assert night.mean() < 0.5 * summer.mean()
    assert winter.mean() > summer.mean()  # snow


def test_same_place_is_more_alike_than_another_place_across_mild_conditions():
    r = render_route(frames=60, seed=0, size=(32, 64), conditions=("summer", "autumn"))
    d = SeqSLAMFrontEnd(size=(32, 64))
    idx, _ = top_k(d.describe(r["autumn"]), d.describe(r["summer"]), 1, similarity=d.similarity)
    recall = GroundTruth.aligned(60, 60, 1).correct_mask(idx).mean()
    assert recall > 0.4  # chance is 3/60 = 0.05; measured 0.79 on 300 frames at 64x128


def test_hard_pair_is_imperfect_for_raw_pixels():
    r = render_route(frames=60, seed=0, size=(32, 64), conditions=("summer", "night"))
    d = RawThumbnail(size=(32, 64))
    idx, _ = top_k(d.describe(r["night"]), d.describe(r["summer"]), 1)
    assert GroundTruth.aligned(60, 60, 1).correct_mask(idx).mean() < 0.5


def test_generate_writes_labelled_folder_and_replaces_old_frames(tmp_path):
    out = tmp_path / "route"
    ds = generate_route(out, frames=5, conditions=("summer", "night"), seed=0, size=(32, 48))
    assert ds.conditions == ["summer", "night"]
    assert [p.name for p in ds["night"].paths] == [f"frame_{i:05d}.png" for i in range(5)]
    readme = (out / "README.txt").read_text()
    assert "SYNTHETIC" in readme and "seed: 0" in readme
    from fdnet.data.images import load_image

    im = load_image(ds["summer"].paths[0])
    assert im.shape == (32, 48, 3)
    np.testing.assert_allclose(im, render_route(5, ("summer",), 0, (32, 48))["summer"][0], atol=1 / 255)
    # Writing a shorter route into the same folder leaves no stale frame behind.
    ds = generate_route(out, frames=3, conditions=("summer",), seed=0, size=(32, 48))
    assert len(ds["summer"]) == 3 and not list((out / "night").glob("*.png"))
    assert not list(out.rglob("*.tmp"))


def test_generate_refuses_a_foreign_non_empty_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="not a synthetic route"):
        generate_route(tmp_path, frames=2, size=(32, 32))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"frames": 0},
        {"conditions": ("summer", "spring")},
        {"conditions": ()},
        {"size": (8, 8)},
        {"conditions": ("night", "night")},
    ],
)
def test_bad_settings_are_config_errors(kwargs):
    with pytest.raises(ConfigError):
        render_route(**{"frames": 2, "size": (32, 32), **kwargs})


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "s"
    assert (
        main(
            [
                "synth",
                "--out",
                str(out),
                "--num-frames",
                "4",
                "--conditions",
                "winter,night",
                "--size",
                "32x64",
                "--seed",
                "2",
            ]
        )
        == 0
    )
    assert "SYNTHETIC" in capsys.readouterr().out
    assert len(list((out / "winter").glob("frame_*.png"))) == 4
    assert main(["synth", "--out", str(out), "--size", "32"]) == 2
    assert "--size" in capsys.readouterr().err
