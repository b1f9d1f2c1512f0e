"""`fdnet reproduce` end to end on a synthetic route with tiny trained runs: every experiment's
numbers, the report in a real headless Chromium, a rerun of one experiment from the cache, and
bad input refused with exit code 2."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pytest

from fdnet.cli import main
from fdnet.reproduce.sections import EXPERIMENTS

# FDNet on a frozen trunk (so the trunk baseline has a run to read), in seconds
TRUNK_RUN = [
    "--set",
    "model.backbone=efficientnet-lite0",
    "--set",
    "model.backbone_block=4",
    "--set",
    "model.input_size=[32,64]",
    "--set",
    "model.widths=[16]",
]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A route (summer, night; 24 frames), a trained run, and the full report on frames 12:24
    (the length study trains its four runs on frames 0:12)."""
    root = tmp_path_factory.mktemp("reproduce")
    route, run, out = root / "route", root / "run", root / "out"
    assert main(["synth", "--out", str(route), "--num-frames", "24", "--conditions", "summer,night"]) == 0
    assert (
        main(
            [
                "train",
                "--data",
                str(route),
                "--preset",
                "tiny",
                "--out",
                str(run),
                "--frames",
                "0:12",
                "--no-progress",
                *TRUNK_RUN,
            ]
        )
        == 0
    )
    # hog: OpenCV loads a BLAS of its own on first use, which --threads must still cover
    args = [
        "reproduce",
        "--data",
        str(route),
        "--checkpoint",
        str(run),
        "--method",
        "fdnet,trunk,sad,hog",
        "--frames",
        "12:24",
        "--length-preset",
        "tiny",
        "--length-train-frames",
        "0:12",
        "--examples",
        "3",
        "--runtime-images",
        "4",
        "--threads",
        "1",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    return {"route": route, "run": run, "out": out, "args": args}


def document(out: Path, name: str) -> dict:
    return json.loads((out / f"{name}.json").read_text())


def test_a_tiny_run_is_called_a_smoke_test_with_its_seeds_recorded(made):
    """The README's example trains FDNet for a few steps: the report says it is a smoke test, and
    every document records the run's seed with its provenance."""
    out = made["out"]
    manifest = document(out, "reproduce")
    assert manifest["checkpoint_run"]["preset"] == "tiny"
    assert "is a smoke test of the pipeline" in manifest["smoke_test"]
    assert "is a smoke test of the pipeline" in (out / "report.html").read_text()
    comparison = document(out, "comparison")
    assert comparison["smoke_test"] == manifest["smoke_test"]
    assert comparison["provenance"]["seeds"]["checkpoint"] == 0 and comparison["provenance"]["command"].startswith(
        "fdnet reproduce --data"
    )
    seeds = document(out, "ablation").get("provenance", {}).get("seeds", {}) if (out / "ablation.json").exists() else {}
    assert all(isinstance(v, int) for k, v in seeds.items() if k != "checkpoint")


def test_every_experiment_writes_its_numbers(made):
    out = made["out"]
    comparison = document(out, "comparison")
    assert [(p["query"], p["reference"]) for p in comparison["pairs"]] == [("summer", "night"), ("night", "summer")]
    for pair in comparison["pairs"]:
        assert [r["method"] for r in pair["results"]] == ["fdnet", "trunk", "sad", "hog"]
        assert all(r["thresholds"] == "500 uniform" and r["num_queries"] == 12 for r in pair["results"])
        assert pair["paper"] is None  # the paper has no synthetic route
    # the command as parsed, flags in the parser's order
    assert comparison["command"] == (
        f"fdnet reproduce --data {made['route']} --frames 12:24 --checkpoint {made['run']} "
        f"--method fdnet,trunk,sad,hog --length-preset tiny --length-train-frames 0:12 --examples 3 "
        f"--runtime-images 4 --out {out} --threads 1 --no-progress"
    )
    lengths = document(out, "lengths")
    assert lengths["lengths"] == [256, 512, 1024, 2048] and len(lengths["accuracy"]) == 8
    assert [t["paper_ms_per_image"] for t in lengths["timing"]] == [20.9, 21.2, 22.6, 28.7]
    assert all(t["ms_per_image"] > 0 for t in lengths["timing"])
    assert (out / "length-runs" / "L1024" / "checkpoints").is_dir()
    disentanglement = document(out, "disentanglement")
    assert {(e["vector"], e["embedding"]) for e in disentanglement["embeddings"]} == {
        ("appearance", "pca"),
        ("appearance", "tsne"),
        ("content", "pca"),
        ("content", "tsne"),
    }
    assert all(-1 <= e["silhouette_full"] <= 1 for e in disentanglement["embeddings"])
    assert disentanglement["content_differences"][0]["num_places"] == 12
    viewpoint = document(out, "viewpoint")
    assert [o["overlap"] for o in viewpoint["methods"][0]["overlaps"]] == [1.0, 0.9, 0.75, 0.65]
    assert [r["overlap"] for r in viewpoint["response"]["rows"]] == [1.0, 0.9, 0.75, 0.65]
    assert viewpoint["response"]["rows"][0]["content_cosine_distance"] == pytest.approx(0, abs=1e-5)
    runtime = document(out, "runtime")
    assert runtime["machine"]["logical_cores"] >= 1
    assert runtime["machine"]["torch_threads"] == runtime["machine"]["blas_threads"] == 1  # --threads 1
    assert {m["method"]: m["paper_ms_per_image"] for m in runtime["methods"]} == {
        "fdnet": 21.2,
        "trunk": None,
        "sad": None,
        "hog": None,
    }
    similarity = document(out, "similarity")
    assert similarity["pairs"][0]["shape"] == [12, 12]
    examples = document(out, "examples")
    assert examples["pairs"][0]["queries"] == [0, 6, 11]
    for name in EXPERIMENTS:
        figures = list((out / "figures" / name).glob("*.png")) + list((out / "figures" / name).glob("*.jpg"))
        assert figures, f"{name} drew no figure"


def _chromium():
    """A Selenium-driven headless Chromium (Debian's chromium + chromium-driver), or skip."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[dev]')")
    from selenium.webdriver.chrome.service import Service

    browser, driver = (
        shutil.which("chromium") or "/usr/bin/chromium",
        shutil.which("chromedriver") or "/usr/bin/chromedriver",
    )
    if not (Path(browser).exists() and Path(driver).exists()):
        pytest.skip("no Chromium here: install Debian's chromium and chromium-driver (.ci/run does so as root)")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    profile = tempfile.mkdtemp(prefix="fdnet-chromium-")
    # The network here is closed: without these Chromium keeps trying to reach Google's services.
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=1280,1000",
        f"--user-data-dir={profile}",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(driver), options=options), profile


def test_the_report_renders_in_headless_chromium(made):
    browser, profile = _chromium()
    try:
        browser.get((made["out"] / "report.html").resolve().as_uri())
        sections = browser.execute_script("return [...document.querySelectorAll('section')].map(s => s.id)")
        assert sections == list(EXPERIMENTS)
        images = browser.execute_script("""
            return [...document.images].map(img => {
                img.scrollIntoView();
                const box = img.getBoundingClientRect();
                return {src: img.src.split(',')[0], complete: img.complete, natural: img.naturalWidth,
                        width: box.width, height: box.height,
                        section: img.closest('section') ? img.closest('section').id : null};
            })""")
        assert {image["section"] for image in images} == set(EXPERIMENTS)
        for image in images:
            assert image["src"] in ("data:image/png;base64", "data:image/jpeg;base64")
            assert image["complete"] and image["natural"] > 0, f"an image in {image['section']} did not decode"
            assert image["width"] > 0 and image["height"] > 0, f"an image in {image['section']} is not displayed"
        tables = browser.execute_script("return document.querySelectorAll('section table').length")
        assert tables >= len(EXPERIMENTS)
        errors = [entry for entry in browser.get_log("browser") if entry["level"] == "SEVERE"]
        assert errors == []
    finally:
        browser.quit()
        shutil.rmtree(profile, ignore_errors=True)


def test_rerunning_one_experiment_describes_nothing_again(made, capsys):
    out = made["out"]
    before = document(out, "comparison")
    assert main([*made["args"], "--experiments", "similarity"]) == 0
    assert "described 0 image set(s)" in capsys.readouterr().err
    assert document(out, "comparison") == before
    html = (out / "report.html").read_text()
    assert all(f'<section id="{name}">' in html for name in EXPERIMENTS)
    assert "--experiments similarity" in html


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--experiments", "tables"], "unknown experiment(s) tables"),
        (["--checkpoint", "other_run"], "give the FDNet run directory exactly once"),
        (["--length-runs", "512"], "expected L=RUN_DIR"),
        (["--overlaps", "100,x"], "'x' is not a number"),
        (["--viewpoint-pair", "summer"], "expected REFERENCE,QUERY"),
        (["--device", "tpu"], "tpu"),
        (["--experiments", ""], "--experiments '': names no experiment"),
        (["--experiments", ","], "--experiments ',': names no experiment"),
    ],
)
def test_bad_input_is_one_error_line_and_exit_2(made, tmp_path, capsys, extra, message):
    args = [
        "reproduce",
        "--data",
        str(made["route"]),
        "--checkpoint",
        str(made["run"]),
        "--method",
        "sad",
        "--out",
        str(tmp_path / "out"),
        *extra,
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet reproduce: error: ") and message in err


def test_missing_data_and_unwritable_output_name_the_path(made, tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert (
        main(["reproduce", "--data", str(missing), "--checkpoint", str(made["run"]), "--out", str(tmp_path / "out")])
        == 2
    )
    assert f"{missing}: dataset folder not found" in capsys.readouterr().err
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert (
        main(["reproduce", "--data", str(made["route"]), "--checkpoint", str(made["run"]), "--out", str(blocked)]) == 2
    )
    assert f"{blocked}: reproduce output folder exists and is not a folder" in capsys.readouterr().err


def test_a_checkpoint_that_is_no_run_is_refused_not_reported(made, tmp_path, capsys):
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(made["route"]),
                "--checkpoint",
                str(tmp_path / "nope"),
                "--method",
                "sad",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    assert f"--checkpoint {tmp_path / 'nope'}: not a run directory" in capsys.readouterr().err
    assert not (tmp_path / "out" / "report.html").exists()


def test_the_protocol_is_a_setting(made, tmp_path, capsys):
    """--protocol vprbench: the comparison under VPR-Bench's protocol (every top-1 score), said in
    its numbers; the paper's protocol stays the default."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(made["out"], out)  # its cached vectors: nothing is described again
    args = [a if a != str(made["out"]) else str(out) for a in made["args"]]
    assert main([*args, "--experiments", "comparison", "--protocol", "vprbench"]) == 0
    comparison = document(out, "comparison")
    assert comparison["protocol"] == "vprbench"
    assert all(r["protocol"] == "vprbench" for pair in comparison["pairs"] for r in pair["results"])
    assert document(made["out"], "comparison")["protocol"] == "recall-over-queries"


def test_baselines_need_no_fdnet_run_and_the_cache_lives_outside_the_report(made, tmp_path, capsys):
    import os

    out = tmp_path / "out"
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(made["route"]),
                "--method",
                "sad,hog",
                "--frames",
                "12:24",
                "--experiments",
                "comparison",
                "--threads",
                "1",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    comparison = document(out, "comparison")
    assert {r["method"] for pair in comparison["pairs"] for r in pair["results"]} == {"sad", "hog"}
    assert not (out / "cache" / "descriptors").exists()
    assert any((Path(os.environ["FDNET_CACHE"]) / "reproduce" / "descriptors").glob("*.npy"))
    mine = tmp_path / "mine"
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(made["route"]),
                "--method",
                "sad",
                "--frames",
                "12:24",
                "--experiments",
                "comparison",
                "--threads",
                "1",
                "--no-progress",
                "--cache",
                str(mine),
                "--out",
                str(tmp_path / "out2"),
            ]
        )
        == 0
    )
    assert any(mine.glob("*.npy"))


def test_a_flag_of_an_experiment_left_out_is_warned_about(tmp_path, capsys):
    """--examples with --experiments comparison did nothing without a word; now a warning names
    the flag and its experiment (a warning: a rerun of one experiment keeps the command's flags)."""
    route = tmp_path / "route"
    assert main(["synth", "--out", str(route), "--num-frames", "8", "--conditions", "summer,night"]) == 0
    capsys.readouterr()
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(route),
                "--method",
                "sad",
                "--experiments",
                "comparison",
                "--examples",
                "3",
                "--runtime-images",
                "4",
                "--threads",
                "1",
                "--no-progress",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert (
        "fdnet reproduce: warning: --examples is for the examples experiment, which this run leaves out "
        "(--experiments): it does nothing here"
    ) in err
    assert "--runtime-images is for the runtime and lengths experiments" in err
    assert "--overlaps" not in err  # left at its default


def test_seeds_below_one_is_one_error_line_and_seeds_outside_the_ablation_a_warning(tmp_path, capsys):
    """--seeds N trains each ablation variant N times: 0 is refused with one line before any work,
    and the flag with the ablation left out is warned about like every experiment's flag."""
    route = tmp_path / "route"
    assert main(["synth", "--out", str(route), "--num-frames", "8", "--conditions", "summer,night"]) == 0
    capsys.readouterr()
    out = tmp_path / "out"
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(route),
                "--frames",
                "4:8",
                "--experiments",
                "ablation",
                "--ablation-preset",
                "tiny",
                "--ablation-train-frames",
                "0:4",
                "--seeds",
                "0",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "error" in line] == [
        "fdnet reproduce: error: --seeds must be a whole number >= 1 (runs per trained variant), got 0"
    ]
    assert not (out / "ablation-runs").exists()
    assert (
        main(
            [
                "reproduce",
                "--data",
                str(route),
                "--method",
                "sad",
                "--experiments",
                "comparison",
                "--seeds",
                "2",
                "--threads",
                "1",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert (
        "--seeds is for the lengths and ablation experiments, which this run leaves out (--experiments): it "
        "does nothing here"
    ) in capsys.readouterr().err
    assert " --seeds 2 " in document(out, "comparison")["command"]
