"""FDNet's training entry point: choosing the start on the validation pair (the trunk block,
``model.backbone_block_candidates``, and the synthetic setting,
``data.synthetic_conditions_candidates``) before training, resuming on the choice, and the same
choice on real Gardens Point and Nordland frames. (The training step and the loop: tests/training.)"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet.config import replace_dotted
from fdnet.methods.fdnet.config import FDNetRunConfig, preset
from fdnet.methods.fdnet.model import FDNet
from fdnet.methods.fdnet.training import train
from fdnet.runs import load_config, load_training_state, load_weights

from conftest import require_shared

# the tiny preset on a frozen trunk with the residual head; blocks 2 (stride 4) and 4 (stride 8)
RESIDUAL_HEAD = {
    "model.backbone": "efficientnet-lite0",
    "model.backbone_block": 2,
    "model.input_size": [32, 64],
    "model.widths": [16],
    "model.content_head": "trunk_residual",
    "model.residual_init": "condition_means",
}
VALIDATION = {
    "validation.reference": "summer",
    "validation.query": "winter",
    "validation.tolerance": 0,
    "validation.every": 4,
}


def make_shifted_dataset(root, n=16, size=(32, 64)):
    """summer: smooth random scenes; winter: the same scenes shifted sideways, darker and noisy,
    so that the two blocks' starts match them differently well (scores that tie would not tell
    the choice apart)."""
    rng = np.random.default_rng(3)
    coarse = rng.random((n, size[0] // 4, size[1] // 4 + 2))
    for k, name in enumerate(("summer", "winter")):
        (root / name).mkdir(parents=True)
        for i in range(n):
            scene = np.kron(coarse[i], np.ones((4, 4)))[:, 4 * k : 4 * k + size[1]]
            image = scene if k == 0 else np.clip(0.6 * scene + 0.35 * rng.random(size), 0, 1)
            Image.fromarray((image * 255).astype(np.uint8)).convert("RGB").save(root / name / f"{i:04d}.png")
    return root


def _config(tmp_path, **overrides) -> FDNetRunConfig:
    data = tmp_path / "data"
    if not data.exists():
        make_shifted_dataset(data)
    return replace_dotted(preset("tiny"), {"data.root": str(data), **RESIDUAL_HEAD, **VALIDATION, **overrides})


def _said(caplog) -> str:
    """What the library logged since the last call (the messages ``fdnet train`` shows)."""
    text = "\n".join(r.getMessage() for r in caplog.records)
    caplog.clear()
    return text


def _weights(run_dir) -> dict[str, torch.Tensor]:
    model = FDNet(load_config(run_dir, FDNetRunConfig).model)
    load_weights(run_dir, model.named_parts())
    return {k: v.clone() for k, v in model.state_dict().items()}


def _rule(selection: dict, order: list[int]) -> int:
    """R@1, ties to AUC, then to the earlier candidate."""
    return max(order, key=lambda b: (selection[str(b)]["recall@1"], selection[str(b)]["auc"], -order.index(b)))


def test_the_block_that_validates_best_is_trained_as_if_it_had_been_set(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="fdnet")
    picks = {}
    for order in ([2, 4], [4, 2]):
        run = tmp_path / f"run-{order[0]}"
        config = _config(tmp_path, **{"model.backbone_block": order[0], "model.backbone_block_candidates": order})
        train(config, run, progress=False)
        selection = load_training_state(run)["method_state"]["block_selection"]
        assert sorted(selection) == ["2", "4"]
        chosen = load_config(run, FDNetRunConfig).model.backbone_block
        assert chosen == _rule(selection, order)
        picks[tuple(order)] = (chosen, selection)
    # the same scores whatever the order, so the same block unless they tie
    (a, sel_a), (b, sel_b) = picks.values()
    for block in ("2", "4"):
        assert sel_a[block]["recall@1"] == pytest.approx(sel_b[block]["recall@1"])
    if (sel_a["2"]["recall@1"], sel_a["2"]["auc"]) != (sel_a["4"]["recall@1"], sel_a["4"]["auc"]):
        assert a == b
    out = _said(caplog)
    assert "trunk block 2: validation R@1" in out and f"training on trunk block {a} (of 2, 4)" in out

    # choosing changed nothing else: the run equals one of the chosen block alone, weight for weight
    alone = tmp_path / "alone"
    train(_config(tmp_path, **{"model.backbone_block": a}), alone, progress=False)
    chosen_run = tmp_path / "run-2"  # candidates [2, 4]
    for (name, x), y in zip(_weights(chosen_run).items(), _weights(alone).values()):
        assert torch.equal(x, y), name


@pytest.fixture
def every_start_scored(monkeypatch):
    """max_minutes=0 stops a training after its first step (a run to resume) and the choice of the
    start after its first candidate; with this fixture the choice scores every start regardless."""
    from fdnet.methods.fdnet import training

    choose = training.choose_start
    monkeypatch.setattr(
        training,
        "choose_start",
        lambda config, real, validation, deadline=None, progress=True: choose(config, real, validation, None, progress),
    )


def test_resume_keeps_the_chosen_block_without_choosing_again(tmp_path, caplog, every_start_scored):
    caplog.set_level(logging.INFO, logger="fdnet")
    config = _config(tmp_path, **{"model.backbone_block_candidates": [2, 4]})
    run = tmp_path / "run"
    summary = train(config, run, max_minutes=0.0, progress=False)
    assert summary["status"] == "time limit"
    chosen = load_config(run, FDNetRunConfig).model.backbone_block
    assert chosen == 4  # these images: block 2's start matches no winter image, block 4's all
    assert (
        "training on trunk block 4 (of 2, 4); model.backbone_block = 2 is the block for runs without a "
        "validation pair"
    ) in _said(caplog)
    selection = load_training_state(run)["method_state"]["block_selection"]
    summary = train(config, run, resume=True, progress=False)  # block 2 requested, as at the start: no refusal
    assert summary["status"] == "finished"
    out = _said(caplog)
    assert "at the start" not in out  # no candidate was scored again
    assert "continuing on trunk block 4, chosen when the run started" in out
    assert load_config(run, FDNetRunConfig).model.backbone_block == chosen
    assert load_training_state(run)["method_state"]["block_selection"] == selection


def test_max_minutes_bounds_the_choice_of_the_start_too(tmp_path, caplog):
    """--max-minutes 8 took 29.7 minutes: the choice of the start ran outside the budget. Now the
    budget counts from the command's start; spent, the choice keeps the best start scored so far
    and training stops after its first step, with a checkpoint."""
    caplog.set_level(logging.INFO, logger="fdnet")
    config = _config(tmp_path, **{"model.backbone_block_candidates": [2, 4]})
    run = tmp_path / "run"
    summary = train(config, run, max_minutes=0.0, progress=False)
    assert summary["status"] == "time limit"
    state = load_training_state(run)
    assert list(state["method_state"]["block_selection"]) == ["2"]  # block 4 was never scored
    assert state["step"] == 1 and load_config(run, FDNetRunConfig).model.backbone_block == 2
    assert "the time ran out while choosing the start, after 1 of 2 candidates" in _said(caplog)


def test_reading_the_images_and_choosing_the_start_show_progress_with_the_time_left(tmp_path, caplog, monkeypatch):
    """The minutes before the first training step were silent: reading the images, each
    candidate's trunk maps and the choice now each show a progress line with elapsed<left (off a
    terminal, a line per interval: here every update)."""
    monkeypatch.setenv("FDNET_PROGRESS_INTERVAL", "0.000001")
    caplog.set_level(logging.INFO, logger="fdnet")
    train(_config(tmp_path, **{"model.backbone_block_candidates": [2, 4]}), tmp_path / "run", progress=True)
    lines = [r.getMessage() for r in caplog.records if r.name == "fdnet.progress"]
    for desc in (
        "reading training images: ",
        "trunk maps [block 2, summer]: ",
        "trunk maps [block 4, winter]: ",
        "choosing the start: 2/2 start (100 %) [",
    ):
        assert any(line.startswith(desc) for line in lines), (desc, lines)
    assert all("<" in line for line in lines if line.startswith("choosing the start"))  # elapsed<left


def test_without_a_validation_pair_the_set_block_is_trained_and_that_is_said(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="fdnet")
    config = _config(
        tmp_path,
        **{
            "model.backbone_block": 4,
            "model.backbone_block_candidates": [2, 4],
            "validation.reference": "",
            "validation.query": "",
        },
    )
    train(config, tmp_path / "run", progress=False)
    assert load_config(tmp_path / "run", FDNetRunConfig).model.backbone_block == 4
    assert (
        "no validation pair to choose a start from (2, 4); training on model.backbone_block = 4, "
        "data.synthetic_conditions = none"
    ) in _said(caplog)
    assert load_training_state(tmp_path / "run")["method_state"]["block_selection"] == {}


def test_synthetic_conditions_are_chosen_with_the_block_and_kept_on_resume(tmp_path, caplog, every_start_scored):
    caplog.set_level(logging.INFO, logger="fdnet")
    config = _config(
        tmp_path,
        **{
            "model.backbone_block_candidates": [2, 4],
            "data.synthetic_conditions_candidates": ["none", "night+contrast"],
        },
    )
    run = tmp_path / "run"
    assert train(config, run, max_minutes=0.0, progress=False)["status"] == "time limit"
    selection = load_training_state(run)["method_state"]["block_selection"]
    order = ["2, synthetic none", "4, synthetic none", "2, synthetic night+contrast", "4, synthetic night+contrast"]
    assert list(selection) == order
    best = max(order, key=lambda k: (selection[k]["recall@1"], selection[k]["auc"], -order.index(k)))
    saved = load_config(run, FDNetRunConfig)
    block, option = best.split(", synthetic ")
    assert saved.model.backbone_block == int(block)
    assert list(saved.data.synthetic_conditions) == ([] if option == "none" else option.split("+"))
    out = _said(caplog)
    assert f"training on trunk block {best} (of {', '.join(order)})" in out
    # the run goes on with what it chose, without scoring again, and equals a run of it alone
    assert train(config, run, resume=True, progress=False)["status"] == "finished"
    assert "at the start" not in _said(caplog)
    alone = tmp_path / "alone"
    train(
        _config(
            tmp_path,
            **{
                "model.backbone_block": saved.model.backbone_block,
                "data.synthetic_conditions": list(saved.data.synthetic_conditions),
            },
        ),
        alone,
        progress=False,
    )
    for (name, x), y in zip(_weights(run).items(), _weights(alone).values()):
        assert torch.equal(x, y), name


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            {"data.synthetic_conditions_candidates": ["none", "fog"]},
            "candidates: fog: data.synthetic_conditions: unknown",
        ),
        ({"data.synthetic_conditions_candidates": ["night", "night"]}, "names a setting twice"),
        ({"data.synthetic_conditions_candidates": ["night"]}, r"synthetic_conditions=\[\] is not among"),
        (
            {
                "data.synthetic_conditions_candidates": ["none", "night"],
                "model.content_head": "encoder",
                "model.backbone": "none",
            },
            "choosing needs model.content_head",
        ),
    ],
)
def test_bad_synthetic_candidates_are_refused_before_any_image_is_read(tmp_path, overrides, message):
    from fdnet.errors import ConfigError

    config = replace_dotted(preset("tiny"), {**RESIDUAL_HEAD, "data.root": str(tmp_path / "missing"), **overrides})
    with pytest.raises(ConfigError, match=message):
        train(config, tmp_path / "run", progress=False)


def _best_by_block(selection: dict) -> dict[int, float]:
    """The best validation R@1 of each candidate block over the synthetic settings."""
    best: dict[int, float] = {}
    for label, scores in selection.items():
        block = int(label.split(",")[0])
        best[block] = max(best.get(block, 0.0), scores["recall@1"])
    return best


@pytest.mark.shared_data
def test_gardens_point_validation_chooses_the_deeper_block_and_nordland_the_shallower_one(tmp_path, every_start_scored):
    """On the training range only: day_left -> night_right 0:100 (tolerance 2) prefers block 11,
    Nordland summer/winter 200:300 (tolerance 0, training 0:300) block 7 (docs/results.md); on
    Gardens Point each with and without the synthetic night copy."""
    from fdnet.cli import main

    gardens = require_shared("gardens_point")
    assert (
        main(
            [
                "train",
                "--data",
                str(gardens),
                "--preset",
                "cpu",
                "--out",
                str(tmp_path / "g"),
                "--conditions",
                "day_right,night_right,day_left",
                "--frames",
                "0:100",
                "--validate-reference",
                "day_left",
                "--validate-query",
                "night_right",
                "--validate-frames",
                "0:100",
                "--validate-tolerance",
                "2",
                "--max-minutes",
                "0",
                "--no-progress",
            ]
        )
        == 0
    )
    selection = load_training_state(tmp_path / "g")["method_state"]["block_selection"]
    assert sorted(selection) == ["11, synthetic night", "11, synthetic none", "7, synthetic night", "7, synthetic none"]
    best = _best_by_block(selection)
    assert best[11] > best[7], selection
    assert load_config(tmp_path / "g", FDNetRunConfig).model.backbone_block == 11

    nordland = require_shared("nordland_trimmed")
    assert (
        main(
            [
                "train",
                "--data",
                str(nordland),
                "--preset",
                "cpu",
                "--out",
                str(tmp_path / "n"),
                "--conditions",
                "summer,winter",
                "--frames",
                "0:300",
                "--validate-reference",
                "summer",
                "--validate-query",
                "winter",
                "--validate-frames",
                "200:300",
                "--set",
                "data.synthetic_conditions_candidates=[]",  # the blocks alone: half the images
                "--max-minutes",
                "0",
                "--no-progress",
            ]
        )
        == 0
    )
    selection = load_training_state(tmp_path / "n")["method_state"]["block_selection"]
    best = _best_by_block(selection)
    assert best[7] > best[11], selection
    assert load_config(tmp_path / "n", FDNetRunConfig).model.backbone_block == 7
