"""`fdnet train calc|netvlad`: the baselines' flags to config, training, resume, and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from PIL import Image

from fdnet import runs
from fdnet.cli import main


def saved_config(run_dir) -> dict:
    return yaml.safe_load((runs.latest_checkpoint(run_dir) / runs.CONFIG_FILE).read_text())


@pytest.fixture
def route(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("summer", "winter"):
        (tmp_path / "route" / name).mkdir(parents=True)
    for i in range(12):
        place = np.kron(rng.random((6, 8, 3)), np.ones((8, 8, 1)))
        for name, img in (("summer", place), ("winter", 0.6 * place + 0.3)):
            pixels = (np.clip(img, 0, 1) * 255).astype(np.uint8)
            Image.fromarray(pixels).save(tmp_path / "route" / name / f"{i:03d}.png")
    return tmp_path / "route"


def test_calc_train_and_resume(route, tmp_path, capsys):
    out = tmp_path / "run"
    # "1:10" is a base-60 integer to YAML; the frame range must reach the config as text
    rc = main(
        [
            "train",
            "calc",
            "--data",
            str(route),
            "--out",
            str(out),
            "--preset",
            "tiny",
            "--no-progress",
            "--frames",
            "1:10",
            "--conditions",
            "summer,winter",
            "--steps",
            "2",
            "--threads",
            "1",
            "--set",
            "train.batch_size=4",
        ]
    )
    assert rc == 0
    config = saved_config(out)
    assert config["method"] == "calc" and config["data"]["frames"] == "1:10"
    assert config["data"]["conditions"] == ["summer", "winter"] and config["train"]["batch_size"] == 4
    assert "--method calc --checkpoint" in capsys.readouterr().out

    assert main(["train", "calc", "--out", str(out), "--resume", "--steps", "3", "--threads", "1"]) == 2
    assert "train.steps: saved 2, requested 3" in capsys.readouterr().err
    assert (
        main(
            [
                "train",
                "calc",
                "--out",
                str(out),
                "--resume",
                "--override",
                "--steps",
                "3",
                "--threads",
                "1",
                "--no-progress",
            ]
        )
        == 0
    )
    log = (out / "log.csv").read_text().splitlines()
    assert log[-1].startswith("3,")
    # resuming with other model settings is refused, naming the setting
    assert main(["train", "calc", "--out", str(out), "--resume", "--set", "model.channels=8,8,4"]) == 2
    assert "model.channels" in capsys.readouterr().err


def test_netvlad_train(route, tmp_path):
    out = tmp_path / "nv"
    rc = main(
        [
            "train",
            "netvlad",
            "--data",
            str(route),
            "--out",
            str(out),
            "--preset",
            "tiny",
            "--tolerance",
            "1",
            "--steps",
            "2",
            "--threads",
            "1",
            "--no-progress",
        ]
    )
    assert rc == 0
    config = saved_config(out)
    assert config["method"] == "netvlad" and config["data"]["tolerance"] == 1
    assert runs.load_training_state(out)["step"] == 2


def test_baselines_train_on_a_dataset_format_split_with_validation(route, tmp_path, capsys):
    """What FDNet had and the baselines lacked: --dataset-format/--split, validation with best/."""
    out = tmp_path / "calc"
    assert (
        main(
            [
                "train",
                "calc",
                "--data",
                str(route),
                "--dataset-format",
                "folders",
                "--split",
                "0:8",
                "--out",
                str(out),
                "--preset",
                "tiny",
                "--steps",
                "4",
                "--threads",
                "1",
                "--no-progress",
                "--set",
                "train.batch_size=4",
                "--validate-reference",
                "summer",
                "--validate-query",
                "winter",
                "--validate-frames",
                "8:12",
                "--validate-every",
                "2",
            ]
        )
        == 0
    )
    config = saved_config(out)
    assert (config["data"]["dataset_format"], config["data"]["split"]) == ("folders", "0:8")
    assert runs.is_run(out / "best")
    assert "recall@1" in (out / "best" / "validation.yaml").read_text()
    rows = (out / "log.csv").read_text().splitlines()
    assert "val_recall@1" in rows[0]


def test_errors_are_one_line(route, tmp_path, capsys):
    assert (
        main(
            [
                "train",
                "netvlad",
                "--data",
                str(route),
                "--conditions",
                "summer",
                "--out",
                str(tmp_path / "a"),
                "--preset",
                "tiny",
            ]
        )
        == 2
    )
    assert "at least 2 conditions" in capsys.readouterr().err
    assert main(["train", "calc", "--data", str(route), "--out", str(tmp_path / "b"), "--set", "train.no_such=1"]) == 2
    assert "no_such" in capsys.readouterr().err
    assert main(["train", "calc", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "c")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["train", "calc", "--out", str(tmp_path / "none"), "--resume"]) == 2
    assert "no run to resume" in capsys.readouterr().err
