"""`fdnet train` / `fdnet extract` on a tiny synthetic dataset."""

import os
import signal

import numpy as np
from PIL import Image

from fdnet.cli import main


def _dataset(root, n=8):
    rng = np.random.default_rng(1)
    for k, name in enumerate(("day", "night")):
        (root / name).mkdir(parents=True)
        for i in range(n):
            Image.fromarray((rng.random((20, 40)) * (255 - 120 * k)).astype(np.uint8)).save(root / name / f"im{i:03d}.png")
    return root


def test_train_resume_extract(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "run"
    assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(out), "--no-progress",
                 "--set", "schedule.joint_steps=1", "--validate-reference", "day", "--validate-query", "night",
                 "--validate-tolerance", "1"]) == 0
    assert "finished at step 6/6" in capsys.readouterr().out
    # a changed setting on --resume is refused with the list of differences ...
    assert main(["train", "--data", str(data), "--out", str(out), "--resume", "--no-progress",
                 "--set", "schedule.joint_steps=2"]) == 2
    err = capsys.readouterr().err
    assert "fdnet train: error:" in err and "schedule.joint_steps: saved 1, requested 2" in err and "--override" in err
    # ... and applied with --override, recorded with the step it took effect
    resumed = ["train", "--data", str(data), "--out", str(out), "--resume", "--override", "--no-progress",
               "--set", "schedule.joint_steps=2"]
    assert main(resumed) == 0
    assert "finished at step 7/7" in capsys.readouterr().out
    import shlex

    from fdnet import runs

    # the record names the command line that made the change (as docs/runs.md shows), not just "fdnet train"
    assert runs.read_changes(out)[0]["step"] == 6
    assert runs.read_changes(out)[0]["command"] == shlex.join(["fdnet", *resumed])
    assert main(["extract", "--checkpoint", str(out), "--images", str(data / "night"),
                 "--out", str(tmp_path / "v.npz"), "--threads", "1"]) == 0
    z = np.load(tmp_path / "v.npz")
    assert z["content"].shape == (8, 16) and z["appearance"].shape == (8, 16)
    assert list(z["names"]) == [f"im{i:03d}.png" for i in range(8)]
    np.testing.assert_allclose(np.linalg.norm(z["content"], axis=1), 1.0, rtol=1e-5)


def test_clear_errors_exit_2(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    assert main(["train", "--data", str(data), "--preset", "nope", "--out", str(tmp_path / "r")]) == 2
    assert "unknown preset 'nope'" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"),
                 "--set", "model.input_size=[18,40]"]) == 2
    assert "height 18" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"),
                 "--conditions", "day"]) == 2
    assert "at least 2 conditions" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "none"), "--resume"]) == 2
    assert "no run to resume" in capsys.readouterr().err
    for bad in ("optim.lr=nan", "optim.lr=-1e-4"):
        assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"),
                     "--set", bad]) == 2
        assert "optim.lr" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--preset", "tiny", "--out", "/proc/fdnet-run"]) == 2
    assert "/proc/fdnet-run" in capsys.readouterr().err
    from fdnet import runs

    assert not runs.is_run(tmp_path / "r")


def test_a_run_directory_in_use_is_refused_with_the_holders_pid(tmp_path, capsys):
    import os

    from fdnet import runs

    data = _dataset(tmp_path / "data")
    with runs.RunLock(tmp_path / "run", command="fdnet train"):
        assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "run"),
                     "--no-progress"]) == 2
    assert f"in use by process {os.getpid()}" in capsys.readouterr().err


def test_train_with_dataset_format_and_named_split(tmp_path, capsys):
    from fdnet.runs import load_config
    from fdnet.methods.fdnet.config import FDNetRunConfig

    root = _dataset(tmp_path / "data", n=10)
    out = tmp_path / "run"
    assert main(["train", "--data", str(root), "--dataset-format", "folders", "--split", "0:6",
                 "--preset", "tiny", "--out", str(out), "--no-progress"]) == 0
    assert "fdnet train: preset tiny, conditions day, night (6, 6 images)" in capsys.readouterr().err
    config = load_config(out, FDNetRunConfig)
    assert (config.data.dataset_format, config.data.split) == ("folders", "0:6")
    # --resume reads the same split from the run's own config
    assert main(["train", "--data", str(root), "--out", str(out), "--resume", "--no-progress"]) == 0
    assert main(["train", "--data", str(root), "--dataset-format", "folders", "--frames", "0:6",
                 "--preset", "tiny", "--out", str(tmp_path / "r2")]) == 2
    assert "--split" in capsys.readouterr().err


def _tiny_train(data, out, *extra):
    return ["train", "--data", str(data), "--preset", "tiny", "--out", str(out), "--no-progress", *extra]


def test_ctrl_c_before_the_first_checkpoint_says_nothing_was_saved(tmp_path, capsys, monkeypatch):
    import fdnet.methods.fdnet.training as training

    data, out = _dataset(tmp_path / "data"), tmp_path / "run"

    def interrupted(config):
        raise KeyboardInterrupt  # Ctrl-C while the images are read

    monkeypatch.setattr(training, "load_training_images", interrupted)
    assert main(_tiny_train(data, out)) == 130
    printed = capsys.readouterr().out
    assert "interrupted before the first checkpoint; nothing was saved" in printed and "--resume" not in printed
    monkeypatch.undo()
    assert main(_tiny_train(data, out)) == 0  # the same command starts the run


def test_ctrl_c_during_training_points_to_the_checkpoint_that_resume_continues(tmp_path, capsys, monkeypatch):
    from fdnet.methods.fdnet.training import FDNetTraining

    data, out = _dataset(tmp_path / "data"), tmp_path / "run"
    step = FDNetTraining.train_step

    def interrupted_at_3(self, index):
        if index == 3:  # Ctrl-C: the loop finishes the step, saves a checkpoint and stops
            os.kill(os.getpid(), signal.SIGINT)
        return step(self, index)

    monkeypatch.setattr(FDNetTraining, "train_step", interrupted_at_3)
    assert main(_tiny_train(data, out)) == 130
    assert f"interrupted; the newest checkpoint is in {out} (continue with --resume)" in capsys.readouterr().out
    from fdnet import runs

    assert runs.load_training_state(out)["step"] == 4  # step 3 (0-based) finished, then saved
    monkeypatch.undo()
    assert main(_tiny_train(data, out, "--resume")) == 0
    assert "finished at step 8/8" in capsys.readouterr().out
