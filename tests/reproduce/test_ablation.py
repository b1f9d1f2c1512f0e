"""The ``ablation`` experiment on tiny runs: it trains the four variants (or takes given runs),
writes its section and ablation.json, reuses finished runs, and refuses what cannot be an
ablation before any work."""

from __future__ import annotations

import json
import re

import pytest

from fdnet.errors import ConfigError
from fdnet.reproduce import reproduce
from fdnet.reproduce.ablation import VARIANTS
from tests.reproduce.conftest import Pixels, settings


def factory(name: str, **options):
    """The stand-in pixels method beside the real FDNet descriptor the variants are read with."""
    if name == "pixels":
        return Pixels(**options)
    from fdnet.descriptors import create

    return create(name, **options)


def ablation(route, out, **changes):
    base = dict(
        experiments=["ablation"],
        conditions=["day", "night"],
        frames="6:10",
        ablation_presets=["tiny"],
        ablation_train_frames="0:6",
        cache=out / "cache",
        progress=False,
    )
    base.update(changes)
    return settings(route, out, **base)


def test_the_experiment_trains_the_variants_and_writes_its_section_and_json(route, tmp_path):
    out = tmp_path / "out"
    said = []
    reproduce(ablation(route, out), factory=factory, log=said.append)
    document = json.loads((out / "ablation.json").read_text())
    assert document["experiment"] == "ablation" and document["variants"] == list(VARIANTS)
    (group,) = document["groups"]
    assert group["preset"] == "tiny" and group["trained_here"] and group["missing"] == []
    runs = {r["variant"]: r for r in group["runs"]}
    assert list(runs) == list(VARIANTS)
    # the schedule each variant was trained at is stated: without the critic there is no critic stage
    assert runs["full"]["schedule"] == {
        "autoencoder": 3,
        "critic": 2,
        "joint": 3,
        "total": 8,
        "critic_updates_per_step": 2,
    }
    assert runs["no-critic"]["schedule"]["critic"] == 0
    assert runs["no-critic"]["schedule"]["critic_updates_per_step"] == 0
    assert all(r["step"] == r["schedule"]["total"] and r["weights_stage"] == "joint" for r in runs.values())
    assert all(r["differences_from_full"] == [] for r in runs.values())
    assert (out / "ablation-runs" / "tiny" / "no-reconstruction" / "checkpoints").is_dir()
    assert [(p["query"], p["reference"]) for p in group["pairs"]] == [("night", "day"), ("day", "night")]
    for pair in group["pairs"]:
        assert [v["variant"] for v in pair["variants"]] == list(VARIANTS)
        for row in pair["variants"]:
            for key in (
                "recall_at_1",
                "recall_at_100_precision",
                "recall_at_100_precision_margin",
                "precision_at_max_recall",
                "auc_pr",
            ):
                assert row[key] is None or 0.0 <= row[key] <= 1.0, key
            assert row["pr_curve"]["recall"]
            if row["variant"] != "full":
                against = row["against_full"]
                assert against["right_only_in_full"] + against["right_only_in_variant"] <= pair["num_queries"]
                assert 0.0 <= against["p_value"] <= 1.0
    assert (out / group["figure"]).is_file()

    html = (out / "report.html").read_text()
    assert re.findall(r'<section id="(\w+)">', html)[-1] == "ablation"
    section = html[html.index('<section id="ablation">') :]
    assert section.count("<table>") == 1 + 2 and "<img" in section
    assert "Without the critic (no D_a, no L_e^adv): R@1" in section
    assert "run-to-run variation, which this experiment does not measure" in section

    # a rerun reuses the finished runs
    said.clear()
    reproduce(ablation(route, out), factory=factory, log=said.append)
    assert sum("finished run in" in line and "reused" in line for line in said) == len(VARIANTS)


def test_variants_trained_with_a_validation_pair_are_read_from_best_and_reused_when_finished(route, tmp_path):
    out = tmp_path / "out"
    validation = {
        "": {
            "validation.reference": "day",
            "validation.query": "night",
            "validation.frames": "3:6",
            "validation.every": 2,
        }
    }
    reproduce(ablation(route, out, ablation_overrides=validation), factory=factory, log=lambda m: None)
    (group,) = json.loads((out / "ablation.json").read_text())["groups"]
    assert group["settings"] == {key: value for key, value in validation[""].items()}
    for run in group["runs"]:
        assert (out / "ablation-runs" / "tiny" / run["variant"] / "best").is_dir()
        assert run["step"] <= run["schedule"]["total"]  # best/'s step
    said = []
    reproduce(ablation(route, out, ablation_overrides=validation), factory=factory, log=said.append)
    assert sum("finished run in" in line and "reused" in line for line in said) == len(VARIANTS)


def test_given_runs_are_grouped_by_their_preset_and_checked_against_their_variant(route, tmp_path):
    out = tmp_path / "out"
    reproduce(ablation(route, out), factory=factory, log=lambda m: None)
    trained = out / "ablation-runs" / "tiny"
    given = [(variant, trained / variant) for variant in VARIANTS]
    other = tmp_path / "other"
    reproduce(
        ablation(route, other, ablation_presets=None, ablation_train_frames=None, ablation_runs=given),
        factory=factory,
        log=lambda m: None,
    )
    (group,) = json.loads((other / "ablation.json").read_text())["groups"]
    assert group["preset"] == "tiny" and not group["trained_here"]
    assert [r["run"] for r in group["runs"]] == [str(folder) for _, folder in given]
    assert not (other / "ablation-runs").exists()

    wrong = [("no-triplet", trained / "no-critic")]
    with pytest.raises(ConfigError, match="no-triplet=.*no-critic: that run was trained as no-critic"):
        reproduce(
            ablation(route, tmp_path / "wrong", ablation_presets=None, ablation_train_frames=None, ablation_runs=wrong),
            factory=factory,
            log=lambda m: None,
        )


def test_the_ablation_is_not_part_of_a_default_run(route, tmp_path):
    out = tmp_path / "out"
    reproduce(
        settings(route, out, experiments=None, methods=["pixels"], conditions=["day", "night"]),
        factory=factory,
        log=lambda m: None,
    )
    assert not (out / "ablation.json").exists()
    assert '<section id="ablation">' not in (out / "report.html").read_text()


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            dict(ablation_presets=None, ablation_train_frames=None),
            "experiment ablation: needs FDNet runs of each variant",
        ),
        (dict(ablation_train_frames="4:8"), "--ablation-train-frames 4:8 overlaps the evaluated frames"),
        (dict(ablation_train_frames=None), "--ablation-preset needs --ablation-train-frames"),
        (dict(ablation_presets=["fast"]), "--ablation-preset fast: unknown FDNet preset"),
        (dict(ablation_overrides={"": {"schedule.joint_step": "3"}}), "schedule.joint_step"),
        (dict(ablation_overrides={"cpu": {"schedule.joint_steps": "3"}}), "cpu is not among the trained presets"),
        (dict(ablation_overrides={"": {"validation.frames": "7:9"}}), "validation.frames=7:9 overlaps the evaluated"),
        (dict(ablation_runs=[("half", "x")]), "half=x: unknown variant"),
        (dict(ablation_runs=[("full", "no/such/run")]), "full=no/such/run: run directory not found"),
    ],
)
def test_what_cannot_be_an_ablation_is_refused_before_any_work(route, tmp_path, changes, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        reproduce(ablation(route, tmp_path / "out", **changes), factory=factory, log=lambda m: None)
    assert not (tmp_path / "out" / "ablation-runs").exists()


def test_ablation_settings_from_the_command_line_are_scoped_by_preset():
    from fdnet.cli.reproduce import _ablation_overrides, _ablation_runs

    assert _ablation_overrides(
        [
            "schedule.joint_steps=10",
            "paper-native:validation.frames=1376:1576",
            "paper-native:schedule.joint_steps=60000",
        ]
    ) == {
        "": {"schedule.joint_steps": "10"},
        "paper-native": {"validation.frames": "1376:1576", "schedule.joint_steps": "60000"},
    }
    assert [(v, str(p)) for v, p in _ablation_runs("full=runs/a, no-critic=runs/b")] == [
        ("full", "runs/a"),
        ("no-critic", "runs/b"),
    ]
    with pytest.raises(ConfigError, match="expected VARIANT=RUN_DIR"):
        _ablation_runs("runs/a")


def test_the_ablation_alone_needs_none_of_the_compared_methods(route, tmp_path):
    from fdnet.errors import NotAvailableError

    def fdnet_only(name: str, **options):
        if name != "fdnet":
            raise NotAvailableError(f"{name}: not available in this test")
        return factory(name, **options)

    out = tmp_path / "out"
    # the default methods: none can run (FDNet has no --checkpoint), which the ablation does not need
    reproduce(ablation(route, out, methods=None), factory=fdnet_only, log=lambda m: None)
    assert json.loads((out / "ablation.json").read_text())["groups"][0]["preset"] == "tiny"
    with pytest.raises(ConfigError, match="none of the methods can run here"):
        reproduce(
            ablation(route, tmp_path / "both", methods=None, experiments=["ablation", "comparison"]),
            factory=fdnet_only,
            log=lambda m: None,
        )


def test_weights_from_before_the_joint_stage_are_named_and_flagged_in_the_report():
    from fdnet.reproduce.ablation import render, weights_stage

    schedule = {"autoencoder": 500, "critic": 800, "joint": 6000, "total": 7300, "critic_updates_per_step": 2}
    assert [weights_stage(schedule, s) for s in (1, 500, 501, 1300, 1301, 7300)] == [
        "auto-encoder",
        "auto-encoder",
        "critic",
        "critic",
        "joint",
        "joint",
    ]
    runs = [
        {
            "variant": v,
            "removes": "x",
            "run": f"runs/{v}",
            "step": step,
            "schedule": schedule,
            "weights_stage": weights_stage(schedule, step),
            "differences_from_full": [],
        }
        for v, step in (("full", 7000), ("no-reconstruction", 1000))
    ]
    document = {
        "groups": [
            {
                "preset": "paper-native",
                "trained_here": False,
                "settings": {},
                "runs": runs,
                "pairs": [],
                "figure": "f.png",
                "missing": ["no-critic", "no-triplet"],
            }
        ]
    }
    texts = [getattr(block, "text", "") for block in render(document)]
    flagged = [t for t in texts if "before any joint step" in t]
    assert flagged == [
        "no-reconstruction's weights (its best by validation) are from step 1000, in its critic "
        "stage, before any joint step: its numbers below are those of its weights before the joint "
        "training, which its validation scored lower."
    ]
    table = next(block for block in render(document) if getattr(block, "rows", None))
    assert [row[3] for row in table.rows] == ["7000 (joint)", "1000 (critic)"]
