"""The runner with stand-in methods: pairs, what a rerun describes again, resuming after Ctrl-C,
methods that learn from the map, methods that cannot run, and settings refused before any work."""

from __future__ import annotations

import json

import pytest

from fdnet.errors import ConfigError, NotAvailableError
from fdnet.reproduce import runner
from fdnet.reproduce.context import Context, build_pairs
from fdnet.reproduce.runner import reproduce

from .conftest import CALLS, FittedPixels, Pixels, factory, settings


def quiet(message: str) -> None:
    pass


def test_every_ordered_pair_of_the_chosen_conditions(route, tmp_path):
    pairs = build_pairs(settings(route, tmp_path / "out", tolerance=1, frames="2:8"))
    assert [(p.reference, p.query) for p in pairs] == [
        ("day", "dusk"),
        ("day", "night"),
        ("dusk", "day"),
        ("dusk", "night"),
        ("night", "day"),
        ("night", "dusk"),
    ]
    split = pairs[0].split
    assert len(split.query) == len(split.reference) == 6
    assert list(split.ground_truth.positives[0]) == [0, 1]  # tolerance 1 at the start of the slice
    chosen = build_pairs(settings(route, tmp_path / "out", conditions=["night", "day"]))
    assert [(p.reference, p.query) for p in chosen] == [("night", "day"), ("day", "night")]


def test_a_rerun_with_one_more_method_describes_only_that_method(route, tmp_path):
    out = tmp_path / "out"
    reproduce(settings(route, out, conditions=["day", "night"]), factory, quiet)
    assert CALLS["pixels.describe"] == 2  # each condition once, shared by both directions
    reproduce(settings(route, out, conditions=["day", "night"], methods=["pixels", "fitted"]), factory, quiet)
    assert CALLS["pixels.describe"] == 2
    assert CALLS["fitted.describe"] > 0
    document = json.loads((out / "comparison.json").read_text())
    assert [r["method"] for r in document["pairs"][0]["results"]] == ["pixels", "fitted"]


def test_an_interrupted_run_resumes_from_what_it_had_described(route, tmp_path):
    out = tmp_path / "out"
    Pixels.interrupt_after = 3  # Ctrl-C while describing the third condition
    with pytest.raises(KeyboardInterrupt):
        reproduce(settings(route, out), factory, quiet)
    assert not (out / "comparison.json").exists()
    Pixels.interrupt_after = None
    CALLS.clear()
    reproduce(settings(route, out), factory, quiet)
    assert CALLS["pixels.describe"] == 1  # only the condition that was interrupted
    assert (out / "report.html").is_file()


def test_a_method_that_learns_from_the_map_is_fitted_on_each_reference_set(route, tmp_path):
    chosen = settings(route, tmp_path / "out", methods=["fitted"])

    def compare_every_pair() -> None:
        ctx = Context(chosen, build_pairs(chosen), factory, quiet)
        handle = ctx.add_method("fitted", "fitted", {}, required=True)
        for pair in ctx.pairs:
            ctx.similarity(handle, pair.split, pair.slug)

    compare_every_pair()
    assert CALLS["fitted.fit"] == 3  # one per reference condition, not one per pair
    # each query set under each pair's fit (6) and each reference set under its own fit (3)
    assert CALLS["fitted.describe"] == 9
    CALLS.clear()
    compare_every_pair()  # a new run on the same output folder
    assert CALLS["fitted.describe"] == 0


def test_default_methods_that_cannot_run_are_reported_with_the_reason(route, tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "DEFAULT_METHODS", ("pixels", "hybridnet"))
    out = tmp_path / "out"
    reproduce(settings(route, out, methods=None, conditions=["day", "night"]), factory, quiet)
    document = json.loads((out / "comparison.json").read_text())
    assert document["skipped"] == [{"method": "hybridnet", "reason": "hybridnet: not available in this test"}]
    assert "hybridnet: not available in this test" in (out / "report.html").read_text()
    with pytest.raises(NotAvailableError):  # named explicitly: an error, not a footnote
        reproduce(settings(route, out, methods=["pixels", "hybridnet"]), factory, quiet)


def test_a_method_needing_more_reference_images_than_the_pairs_have_is_skipped_or_refused(route, tmp_path, monkeypatch):
    # trunk-whitened learns an L-dimensional whitening from each comparison's references: L + 1 images
    monkeypatch.setattr(runner, "DEFAULT_METHODS", ("pixels", "fitted"))
    monkeypatch.setattr(FittedPixels, "fewest", 10_000)
    out = tmp_path / "out"
    reproduce(settings(route, out, methods=None, conditions=["day", "night"]), factory, quiet)
    (skipped,) = json.loads((out / "comparison.json").read_text())["skipped"]
    assert skipped["method"] == "fitted" and "needs at least 10000" in skipped["reason"]
    assert CALLS["fitted.fit"] == 0
    with pytest.raises(ConfigError, match="fitted: learns from each comparison's reference images"):
        reproduce(settings(route, out, methods=["pixels", "fitted"]), factory, quiet)


def test_rerunning_one_experiment_keeps_the_other_sections(route, tmp_path):
    out = tmp_path / "out"
    reproduce(settings(route, out, conditions=["day", "night"], experiments=["comparison", "examples"]), factory, quiet)
    comparison = (out / "comparison.json").read_text()
    reproduce(
        settings(
            route,
            out,
            conditions=["day", "night"],
            experiments=["examples"],
            command="fdnet reproduce --experiments examples",
        ),
        factory,
        quiet,
    )
    assert (out / "comparison.json").read_text() == comparison
    html = (out / "report.html").read_text()
    section = html[html.index('<section id="comparison">') : html.index('<section id="lengths">')]
    assert "<table>" in section and "made by another command" in section
    assert "fdnet reproduce --experiments examples" in html[: html.index("<section")]
    # figures an earlier run drew for pairs or methods no longer run are removed
    stale = out / "figures" / "examples" / "examples_old_pair.jpg"
    stale.write_bytes(b"from an earlier run")
    reproduce(settings(route, out, conditions=["day", "night"], experiments=["examples"]), factory, quiet)
    assert not stale.exists() and len(list((out / "figures" / "examples").iterdir())) == 2


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(experiments=["tables"]), "unknown experiment(s) tables"),
        (dict(methods=["nope"]), "unknown method(s) nope"),
        (dict(overlaps=(1.0, 1.5)), "overlap 1.5"),
        (dict(examples=0), "--examples must be >= 1"),
        (dict(experiments=["lengths"]), "experiment lengths: needs four FDNet runs"),
        (dict(experiments=["disentanglement"]), "experiment disentanglement: needs FDNet"),
    ],
)
def test_settings_that_cannot_work_are_refused(route, tmp_path, changes, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        reproduce(settings(route, tmp_path / "out", **changes), factory, quiet)


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(length_preset="tiny", length_train_frames="0:6", frames="4:10"), "overlaps the evaluated frames"),
        (dict(length_preset="tiny"), "needs --length-train-frames"),
        (dict(length_runs={512: "no/such/run"}), "512=no/such/run: run directory not found"),
        (dict(viewpoint_pair=("day", "fog")), "--viewpoint-pair day,fog: no such pair"),
    ],
)
def test_experiment_settings_are_checked_before_any_work(route, tmp_path, changes, message):
    with pytest.raises(ConfigError, match=message):
        reproduce(settings(route, tmp_path / "out", experiments=None, **changes), factory, quiet)
    assert CALLS["pixels.describe"] == 0


def test_an_output_path_that_is_a_file_is_refused_before_any_work(route, tmp_path):
    out = tmp_path / "out"
    out.write_text("not a folder")
    with pytest.raises(ConfigError, match="exists and is not a folder"):
        reproduce(settings(route, out), factory, quiet)
    assert CALLS["pixels.describe"] == 0


def test_comparison_shows_r100p_under_the_default_acceptance_rule_beside_raw(route, tmp_path):
    from fdnet.decisions.acceptance import DEFAULT_ACCEPTANCE

    out = tmp_path / "out"
    reproduce(settings(route, out, conditions=["day", "night"]), factory, quiet)
    document = json.loads((out / "comparison.json").read_text())
    assert document["acceptance"] == DEFAULT_ACCEPTANCE
    result = document["pairs"][0]["results"][0]
    assert result["acceptance"] == "raw"  # the paper's columns stay the best-match similarity's
    per = result["per_acceptance"]
    assert per["raw"]["recall_at_100_precision"] == result["recall_at_100_precision"]
    html = (out / "report.html").read_text()
    start = html.index('<section id="comparison">')
    section = html[start : html.index("</table>", start)]
    assert f"<th>R@100P</th><th>R@100P {DEFAULT_ACCEPTANCE}</th>" in section
    assert f"{per[DEFAULT_ACCEPTANCE]['recall_at_100_precision']:.3f}" in section


def test_the_manifest_and_every_experiment_record_their_provenance(route, tmp_path):
    out = tmp_path / "out"
    reproduce(settings(route, out, conditions=["day", "night"]), factory, quiet)
    for name in ("reproduce", "comparison"):
        document = json.loads((out / f"{name}.json").read_text())
        record = document["provenance"]
        assert record["command"] == "fdnet reproduce (test)" and record["seeds"] == {"checkpoint": None}
        assert {"fdnet_version", "git", "libraries", "device", "cpu"} <= set(record)
        assert document["smoke_test"] is None  # no FDNet run was given


def test_every_experiment_loads_its_own_module():
    """The runner finds each experiment's module by its name (the runtime experiment's module is
    table5_runtime); each module says it is that experiment."""
    from fdnet.reproduce.sections import EXPERIMENTS

    assert {name: runner.experiment_module(name).NAME for name in EXPERIMENTS} == {name: name for name in EXPERIMENTS}
    assert runner.experiment_module("runtime").__name__ == "fdnet.reproduce.table5_runtime"
