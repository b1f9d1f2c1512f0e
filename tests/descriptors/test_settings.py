"""Every method's settings dataclass: declared once, read by the registry and the command line,
checked explicitly (a bad value is one ConfigError naming the method and the setting)."""

from __future__ import annotations

import dataclasses

import pytest

from fdnet.cli import main
from fdnet.descriptors import registry
from fdnet.descriptors.settings import MethodSettings
from fdnet.errors import ConfigError

from conftest import write_day_dusk_route

#: one bad value per method: (method, setting, value as --method-set gives it, as Python gives it)
BAD_VALUES = [
    ("fdnet", "batch_size", "0", 0),
    ("trunk", "block", "x", "x"),
    ("trunk-whitened", "power", "-1", -1),
    ("raw", "size", "big", "big"),
    ("sad", "patch_size", "0", 0),
    ("hog", "grey", "maybe", "maybe"),
    ("gist", "image_size", "big", "big"),
    ("dbow", "depth", "x", "x"),
    ("conv3", "dim", "x", "x"),
    ("landmarks", "max_regions", "x", "x"),
    ("netvlad", "threads", "0", 0),
    ("calc", "bf16", "maybe", "maybe"),
    ("hybridnet", "dim", "-1", -1),
    ("onnx", "channels", "hsv", "hsv"),
    ("precomputed", "normalise", "l1", "l1"),
]


def test_every_method_declares_a_frozen_settings_dataclass():
    for spec in registry.all_specs():
        settings = spec.descriptor_class().Settings
        assert issubclass(settings, MethodSettings) and settings is not MethodSettings, spec.name
        assert settings.method == spec.name
        assert dataclasses.is_dataclass(settings) and settings.__dataclass_params__.frozen, spec.name
        assert all(f.default is not dataclasses.MISSING for f in dataclasses.fields(settings)), spec.name
        assert registry.setting_names(spec.name) == tuple(f.name for f in dataclasses.fields(settings))
    assert {spec.name for spec in registry.all_specs()} == {name for name, *_ in BAD_VALUES}


@pytest.mark.parametrize("method, setting, text, value", BAD_VALUES)
def test_a_bad_value_is_a_config_error_naming_the_method_and_the_setting(method, setting, text, value):
    with pytest.raises(ConfigError, match=f"^{method}: {setting}="):
        registry.create(method, **{setting: value})


@pytest.mark.parametrize("method, setting, text, value", BAD_VALUES)
def test_a_bad_value_is_the_commands_one_line_error(method, setting, text, value, tmp_path, rng, capsys):
    route = write_day_dusk_route(tmp_path / "route", rng, places=3)
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(route),
                "--reference",
                "day",
                "--query",
                "dusk",
                "--method",
                method,
                "--method-set",
                f"{setting}={text}",
                "--workers",
                "0",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith(f"fdnet evaluate: error: {method}: {setting}="), err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_settings_objects_and_overrides_build_the_same_descriptor():
    from fdnet.descriptors.gist import GistDescriptor, GistSettings

    by_object = GistDescriptor(GistSettings(image_size=64))
    by_override = GistDescriptor(image_size=64)
    both = GistDescriptor(GistSettings(image_size=32), image_size=64)
    assert by_object.conf == by_override.conf == both.conf == GistSettings(image_size=64)
    assert by_object.fingerprint() == by_override.fingerprint() == both.fingerprint()
    with pytest.raises(dataclasses.FrozenInstanceError):
        by_object.conf.image_size = 32


def test_an_unknown_setting_lists_the_methods_settings():
    with pytest.raises(ConfigError, match="method 'sad' has no setting.s. dim; its settings: size, patch_size"):
        registry.create("sad", dim=3)
    from fdnet.descriptors.classic import SeqSLAMFrontEnd

    with pytest.raises(ConfigError, match="its settings: size, patch_size"):
        SeqSLAMFrontEnd(dim=3)


def test_fingerprints_are_those_of_the_constructor_keywords_they_replace():
    """Settings objects change how a descriptor is built, not what it is: the fingerprints the
    databases and index files hold stay those of the same settings before."""
    from fdnet.descriptors.classic import HOGDescriptor, RawThumbnail, SeqSLAMFrontEnd

    assert RawThumbnail().fingerprint() == RawThumbnail(size="32x64").fingerprint()
    assert SeqSLAMFrontEnd(patch_size=8).settings() == {
        "input_size": [32, 64],
        "patch_size": 8,
        "grey": True,
        "similarity": "negative mean absolute difference",
    }
    assert HOGDescriptor().settings() == {
        "input_size": [512, 512],
        "cell_size": 16,
        "block_size": 16,
        "block_stride": 8,
        "orientations": 9,
        "grey": False,
        "implementation": "opencv",
        "similarity": "cosine",
    }


def test_an_error_loading_weights_keeps_its_own_type_and_cause(monkeypatch, tmp_path):
    """Settings are checked before anything is loaded; what goes wrong while loading is not
    relabelled as an invalid setting."""
    from fdnet.descriptors import alexnet

    def broken(*args, **kwargs):
        raise ValueError("a bug in the loader")

    monkeypatch.setattr(alexnet, "AlexNetTrunk", broken)
    weights = tmp_path / "alexnet.safetensors"
    weights.write_bytes(b"x")
    with pytest.raises(ValueError, match="a bug in the loader"):
        registry.create("conv3", weights=str(weights), device="cpu")
    with pytest.raises(ConfigError, match="^conv3: seed=-1: must be a whole number >= 0"):
        registry.create("conv3", weights=str(weights), seed=-1)


def test_two_bare_values_of_one_file_flag_are_refused():
    import argparse

    from fdnet.cli.common import method_options

    args = argparse.Namespace(method="fdnet,trunk", checkpoint=["runs/a", "runs/b"], method_set=[])
    with pytest.raises(ConfigError, match="--checkpoint gives fdnet 2 values .runs/a, runs/b."):
        method_options(args, "fdnet")
    args.checkpoint = ["trunk:runs/b", "runs/a"]  # the scoped value wins for trunk; fdnet takes the bare one
    assert method_options(args, "trunk") == {"checkpoint": "runs/b"}
    assert method_options(args, "fdnet") == {"checkpoint": "runs/a"}
