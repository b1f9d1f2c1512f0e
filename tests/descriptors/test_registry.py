"""The method registry: one line per method, and every list of methods generated from it."""

from __future__ import annotations

from pathlib import Path

import pytest

from fdnet.descriptors import registry
from fdnet.errors import ConfigError

DOCS = Path(__file__).resolve().parents[2] / "docs" / "methods.md"


def test_device_column_matches_the_descriptors_device_setting():
    for name in registry.available_methods():
        assert registry.takes_device(name) == registry.spec(name).torch, name


def test_trained_methods_presets_match_their_config_modules():
    assert registry.trained_methods()[0] == "fdnet"
    for name in registry.trained_methods():
        spec = registry.spec(name)
        assert set(spec.presets) == set(spec.config_module().PRESETS), name
        assert spec.default_preset in spec.presets
        assert isinstance(spec.preset(), spec.config_class())
        assert callable(spec.train_function())
        assert spec.package == f"fdnet.methods.{name}"


def test_reproduce_list_is_the_registry_column_fdnet_and_the_trunk_first():
    from fdnet.reproduce.runner import DEFAULT_METHODS

    assert DEFAULT_METHODS == registry.reproduce_methods()
    assert DEFAULT_METHODS[:3] == ("fdnet", "trunk", "trunk-whitened")
    # every method but the thumbnail and the two that read a user's file (an ONNX model, vectors)
    assert set(DEFAULT_METHODS) == {n for n in registry.available_methods() if n not in ("raw", "onnx", "precomputed")}


def test_cli_choices_and_help_come_from_the_registry(capsys):
    from fdnet.cli import build_parser

    parser = build_parser()
    train = parser._subparsers._group_actions[0].choices["train"]
    method = next(a for a in train._actions if a.dest == "method")
    assert list(method.choices) == registry.trained_methods()
    preset = next(a for a in train._actions if a.dest == "preset")
    for name in registry.trained_methods():
        spec = registry.spec(name)
        assert f"{name}: {'|'.join(spec.presets)} (default {spec.default_preset})" in preset.help
    evaluate = parser._subparsers._group_actions[0].choices["evaluate"].format_help()
    assert ", ".join(registry.torch_methods()) in " ".join(evaluate.split())


def test_docs_table_is_the_generated_one():
    assert (
        registry.methods_markdown() in DOCS.read_text()
    ), "docs/methods.md's table is out of date: paste `fdnet methods --markdown`"


def test_unknown_names_and_untrained_methods_are_config_errors():
    with pytest.raises(ConfigError, match="unknown method 'nope'"):
        registry.spec("nope")
    with pytest.raises(ConfigError, match="sad is not a trained method"):
        registry.spec("sad").preset()
    with pytest.raises(ConfigError, match="unknown preset 'paper' for calc; available: default, small, tiny"):
        registry.spec("calc").preset("paper")
