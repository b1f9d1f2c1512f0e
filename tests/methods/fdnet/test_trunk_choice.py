"""Choosing the trunk's backbone and block on a validation pair (FDNet's rule)."""

from __future__ import annotations

import pytest
import yaml

from fdnet.data.dataset import RouteDataset
from fdnet.data.split import aligned_split
from fdnet.descriptors import create
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.trunk_choice import (
    Candidate,
    choose_trunk,
    parse_candidates,
    pick_best,
    read_choice,
    write_choice,
)

from conftest import write_day_night_route


def test_rule_r1_then_auc_then_earlier():
    s = lambda r1, auc: {"recall_at_1": r1, "auc_pr": auc}  # noqa: E731
    assert pick_best([s(0.5, 0.9), s(0.6, 0.1), s(0.55, 1.0)]) == 1
    assert pick_best([s(0.6, 0.5), s(0.6, 0.7), s(0.6, 0.6)]) == 1
    assert pick_best([s(0.6, 0.7), s(0.6, 0.7)]) == 0
    with pytest.raises(ConfigError):
        pick_best([])


def test_candidates_parse_and_are_checked():
    assert parse_candidates("efficientnet-lite0:7, lite2:12,lite0:7") == [
        Candidate("efficientnet-lite0", 7),
        Candidate("efficientnet-lite2", 12),
    ]
    for bad, message in (
        ("lite0", "expected BACKBONE:BLOCK"),
        ("lite3:4", "not a shipped backbone"),
        ("lite0:16", "blocks 0..15"),
        ("", "no candidates"),
        ("lite1:x", "expected"),
    ):
        with pytest.raises(ConfigError, match=message):
            parse_candidates(bad)


@pytest.fixture
def route(tmp_path):
    return write_day_night_route(tmp_path, 6)


def test_choice_is_the_best_candidate_and_trunk_methods_read_it(route, tmp_path):
    split = aligned_split(RouteDataset.from_folder(route), "day", "night", 0, None, None)
    candidates = parse_candidates("lite0:4,lite0:7,lite1:8")
    choice = choose_trunk(
        split, candidates, input_size=(32, 64), options={"bf16": False}, pipeline=PipelineSettings(workers=0)
    )
    assert [(s["backbone"], s["block"]) for s in choice.scores] == [(c.backbone, c.block) for c in candidates]
    assert choice.chosen == candidates[pick_best(choice.scores)]
    # each score is what evaluating that trunk alone gives
    from fdnet.evaluation.experiment import evaluate_method

    alone = evaluate_method(
        create("trunk", backbone="efficientnet-lite1", block=8, input_size=[32, 64], bf16=False),
        split,
        pipeline=PipelineSettings(workers=0),
    ).to_dict(include_curve=False)
    assert choice.scores[2]["recall_at_1"] == alone["recall_at_n"]["1"]
    assert choice.scores[2]["auc_pr"] == pytest.approx(alone["auc_pr"])
    path = tmp_path / "choice.yaml"
    write_choice(path, choice)
    assert yaml.safe_load(path.read_text())["rule"].startswith("highest validation R@1")
    trunk = create("trunk", choice=str(path), bf16=False)
    assert (trunk.settings()["backbone"], trunk.settings()["block"], trunk.input_size) == (
        f"{choice.chosen.backbone} (ImageNet)",
        choice.chosen.block,
        (32, 64),
    )
    assert create("trunk", choice=str(path), block=5, bf16=False).settings()["block"] == 5  # explicit wins


def test_whitened_candidates_learn_from_the_pairs_references(route):
    split = aligned_split(RouteDataset.from_folder(route), "day", "night", 0, None, None)
    choice = choose_trunk(
        split,
        parse_candidates("lite0:7"),
        input_size=(32, 64),
        whitened=True,
        options={"dim": 3, "bf16": False},
        pipeline=PipelineSettings(workers=0),
    )
    assert choice.method == "trunk-whitened" and choice.scores[0]["dim"] == 3
    assert choice.scores[0]["fitted_on"] == "reference images (6)"
    with pytest.raises(ConfigError, match="block is what is being chosen"):
        choose_trunk(split, parse_candidates("lite0:7"), options={"block": 3})


def test_bad_choice_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        read_choice(tmp_path / "missing.yaml")
    (tmp_path / "other.yaml").write_text("a: 1\n")
    with pytest.raises(ConfigError, match="not a trunk choice file"):
        read_choice(tmp_path / "other.yaml")
    (tmp_path / "broken.yaml").write_text("format: fdnet-trunk-choice-1\nbackbone: efficientnet-lite0\n")
    with pytest.raises(ConfigError, match="lacks a valid"):
        read_choice(tmp_path / "broken.yaml")
    with pytest.raises(ConfigError, match="not both"):
        create("trunk", checkpoint=str(tmp_path), choice=str(tmp_path / "other.yaml"))
