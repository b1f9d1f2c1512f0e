"""One check everywhere: evaluate, calibrate and loop-closure refuse a trained method on the
frames it was trained on (fdnet.runs.held_out), unless asked to measure it anyway."""

import dataclasses

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet.cli import main
from fdnet.methods.fdnet.config import preset
from fdnet.methods.fdnet.model import FDNet
from fdnet.runs import save_checkpoint


@pytest.fixture
def route_and_run(tmp_path):
    root = tmp_path / "route"
    rng = np.random.default_rng(0)
    for condition in ("day", "night"):
        (root / condition).mkdir(parents=True)
        for i in range(12):
            Image.fromarray(rng.integers(0, 256, size=(16, 32, 3)).astype(np.uint8)).save(
                root / condition / f"{i:03d}.png"
            )
    config = preset("tiny")
    config = dataclasses.replace(
        config, data=dataclasses.replace(config.data, root=str(root), conditions=["day", "night"], frames="0:6")
    )
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "run", FDNet(config.model).named_parts(), config, state={"step": 1})
    return root, tmp_path / "run"


def evaluate(root, run, frames, *extra):
    return main(
        [
            "evaluate",
            "--data",
            str(root),
            "--reference",
            "day",
            "--query",
            "night",
            "--frames",
            frames,
            "--tolerance",
            "0",
            "--method",
            "fdnet",
            "--checkpoint",
            str(run),
            *extra,
        ]
    )


def test_evaluate_refuses_the_training_frames_and_takes_held_out_ones(route_and_run, capsys):
    root, run = route_and_run
    assert evaluate(root, run, "4:10") == 2
    err = capsys.readouterr().err
    assert "fdnet evaluate: error: " in err and "was trained on frames 0:6" in err
    assert "frames 4:10 overlap them" in err and "--allow-training-frames" in err
    assert evaluate(root, run, "6:12") == 0
    assert evaluate(root, run, "4:10", "--allow-training-frames") == 0


def test_calibrate_and_loop_closure_use_the_same_check(route_and_run, tmp_path, capsys):
    root, run = route_and_run
    assert (
        main(
            [
                "calibrate",
                "--data",
                str(root),
                "--reference",
                "day",
                "--query",
                "night",
                "--frames",
                "0:12",
                "--tolerance",
                "0",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--accept",
                "margin",
                "--out",
                str(tmp_path / "cal.yaml"),
            ]
        )
        == 2
    )
    assert "fdnet calibrate: error: " in capsys.readouterr().err
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,night",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--exclude-last",
                "1",
                "--sequence-length",
                "1",
                "--threshold",
                "0.5",
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 2
    )
    assert "was trained on frames 0:6" in capsys.readouterr().err
    assert (
        main(
            [
                "loop-closure",
                "--data",
                str(root),
                "--conditions",
                "day,night",
                "--frames",
                "6:12",
                "--method",
                "fdnet",
                "--checkpoint",
                str(run),
                "--exclude-last",
                "1",
                "--sequence-length",
                "1",
                "--threshold",
                "0.5",
                "--out",
                str(tmp_path / "e.csv"),
            ]
        )
        == 0
    )
