"""`fdnet train` / `fdnet extract` on a tiny synthetic dataset."""

import os
import signal

import numpy as np

from fdnet.cli import main

from conftest import write_day_night_set


def _dataset(root, n=8):
    return write_day_night_set(root, n, prefix="im")


def test_train_resume_extract(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(out),
                "--no-progress",
                "--set",
                "schedule.joint_steps=1",
                "--validate-reference",
                "day",
                "--validate-query",
                "night",
                "--validate-tolerance",
                "1",
            ]
        )
        == 0
    )
    assert "finished at step 6/6" in capsys.readouterr().out
    # a changed setting on --resume is refused with the list of differences ...
    assert (
        main(
            [
                "train",
                "--data",
                str(data),
                "--out",
                str(out),
                "--resume",
                "--no-progress",
                "--set",
                "schedule.joint_steps=2",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "fdnet train: error:" in err and "schedule.joint_steps: saved 1, requested 2" in err and "--override" in err
    # ... and applied with --override, recorded with the step it took effect
    resumed = [
        "train",
        "--data",
        str(data),
        "--out",
        str(out),
        "--resume",
        "--override",
        "--no-progress",
        "--set",
        "schedule.joint_steps=2",
    ]
    assert main(resumed) == 0
    assert "finished at step 7/7" in capsys.readouterr().out
    import shlex

    from fdnet import runs

    # the record names the command line that made the change (as docs/runs.md shows), not just "fdnet train"
    assert runs.read_changes(out)[0]["step"] == 6
    assert runs.read_changes(out)[0]["command"] == shlex.join(["fdnet", *resumed])
    assert (
        main(
            [
                "extract",
                "--checkpoint",
                str(out),
                "--images",
                str(data / "night"),
                "--out",
                str(tmp_path / "v.npz"),
                "--threads",
                "1",
            ]
        )
        == 0
    )
    z = np.load(tmp_path / "v.npz")
    assert z["content"].shape == (8, 16) and z["appearance"].shape == (8, 16)
    assert list(z["names"]) == [f"im{i:03d}.png" for i in range(8)]
    np.testing.assert_allclose(np.linalg.norm(z["content"], axis=1), 1.0, rtol=1e-5)


def test_clear_errors_exit_2(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    assert main(["train", "--data", str(data), "--preset", "nope", "--out", str(tmp_path / "r")]) == 2
    assert "unknown preset 'nope'" in capsys.readouterr().err
    assert (
        main(
            [
                "train",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "r"),
                "--set",
                "model.input_size=[18,40]",
            ]
        )
        == 2
    )
    assert "height 18" in capsys.readouterr().err
    assert (
        main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"), "--conditions", "day"])
        == 2
    )
    assert "at least 2 conditions" in capsys.readouterr().err
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "none"), "--resume"]) == 2
    assert "no run to resume" in capsys.readouterr().err
    for bad in ("optim.lr=nan", "optim.lr=-1e-4"):
        assert main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"), "--set", bad]) == 2
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
        assert (
            main(["train", "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "run"), "--no-progress"])
            == 2
        )
    assert f"in use by process {os.getpid()}" in capsys.readouterr().err


def test_train_with_dataset_format_and_named_split(tmp_path, capsys):
    from fdnet.methods.fdnet.config import FDNetRunConfig
    from fdnet.runs import load_config

    root = _dataset(tmp_path / "data", n=10)
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(root),
                "--dataset-format",
                "folders",
                "--split",
                "0:6",
                "--preset",
                "tiny",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "fdnet train: preset tiny, conditions day, night (6, 6 images)" in capsys.readouterr().err
    config = load_config(out, FDNetRunConfig)
    assert (config.data.dataset_format, config.data.split) == ("folders", "0:6")
    # --resume reads the same split from the run's own config
    assert main(["train", "--data", str(root), "--out", str(out), "--resume", "--no-progress"]) == 0
    assert (
        main(
            [
                "train",
                "--data",
                str(root),
                "--dataset-format",
                "folders",
                "--frames",
                "0:6",
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "r2"),
            ]
        )
        == 2
    )
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


# ---------------------------------------------------------------- every trained method through one command
import dataclasses  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import pytest  # noqa: E402

from fdnet.methods.settings import DataConfig, RuntimeConfig, ValidationConfig  # noqa: E402


@dataclass
class DummyTrain:
    steps: int = 100


@dataclass
class DummyRunConfig:
    """A trained method as small as one can be: one weight learnt towards the images' mean."""

    method: str = "dummy"
    preset: str = ""
    train: DummyTrain = field(default_factory=DummyTrain)
    runtime: RuntimeConfig = field(default_factory=lambda: RuntimeConfig(checkpoint_every=2, log_every=1))
    data: DataConfig = field(default_factory=DataConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)

    @property
    def total_steps(self) -> int:
        return self.train.steps

    def with_total_steps(self, steps: int) -> "DummyRunConfig":
        return dataclasses.replace(self, train=DummyTrain(steps=steps))


PRESETS = {"tiny": lambda: DummyRunConfig(preset="tiny", train=DummyTrain(steps=3))}


def train_dummy(
    config, run_dir, resume=False, override=False, max_minutes=None, progress=True, command="fdnet train dummy"
):
    import torch

    from fdnet.training.data import route_images, training_route
    from fdnet.training.loop import LoopSettings, TrainingMethod, run_training, training_device

    class DummyTraining(TrainingMethod):
        name = "dummy"
        log_columns = ("loss",)

        def __init__(self):
            self.config, self.input_size = config, (8, 8)
            self.device = training_device(config.runtime)
            data = route_images(training_route(config.data), self.input_size, why="dummy")
            self.mean = torch.cat(data.images).float().mean().to(self.device) / 255
            self.weight = torch.nn.Linear(1, 1, bias=False).to(self.device)
            self.optimizer = torch.optim.SGD(self.weight.parameters(), lr=0.5)

        def modules(self):
            return {"dummy": self.weight}

        def optimizers(self):
            return {"dummy": self.optimizer}

        def loop_settings(self):
            rt = config.runtime
            return LoopSettings(config.train.steps, rt.checkpoint_every, rt.log_every)

        def train_step(self, step):
            loss = (self.weight.weight.sum() - self.mean) ** 2
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            return {"loss": float(loss.detach())}

    return run_training(
        lambda: (DummyTraining(), None),
        run_dir,
        resume=resume,
        override=override,
        max_minutes=max_minutes,
        progress=progress,
        command=command,
        runtime=config.runtime,
    )


@pytest.fixture
def dummy_method(monkeypatch):
    """Adding a trained method: its own package (here this module) and one registry line."""
    from fdnet.descriptors import registry

    monkeypatch.setitem(
        registry._METHODS,
        "dummy",
        registry.MethodSpec(
            "dummy",
            "test stand-in",
            "fdnet.descriptors.classic:RawThumbnail",
            config=f"{__name__}:DummyRunConfig",
            trainer=f"{__name__}:train_dummy",
            presets=("tiny",),
            default_preset="tiny",
        ),
    )
    return "dummy"


def test_a_trained_method_added_by_one_registry_line_trains_with_every_shared_flag(tmp_path, capsys, dummy_method):
    from fdnet import runs

    data, out = _dataset(tmp_path / "data"), tmp_path / "run"
    assert (
        main(
            [
                "train",
                "dummy",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(out),
                "--no-progress",
                "--threads",
                "1",
                "--device",
                "cpu",
                "--steps",
                "4",
                "--set",
                "runtime.log_every=2",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "finished at step 4/4" in printed and f"use it with --method dummy --checkpoint {out}" in printed
    assert "min of training (" in printed and "min in all)" in printed
    config = runs.load_config(out, DummyRunConfig)
    assert (config.preset, config.runtime.threads, config.runtime.device, config.runtime.log_every) == (
        "tiny",
        1,
        "cpu",
        2,
    )
    assert main(["train", "dummy", "--out", str(out), "--resume", "--steps", "5", "--no-progress"]) == 2
    assert "train.steps: saved 4, requested 5" in capsys.readouterr().err
    assert main(["train", "dummy", "--out", str(out), "--resume", "--override", "--steps", "5", "--no-progress"]) == 0
    assert runs.load_training_state(out)["step"] == 5
    assert main(["train", "dummy", "--data", str(data), "--preset", "cpu", "--out", str(tmp_path / "r2")]) == 2
    assert "unknown preset 'cpu' for dummy; available: tiny" in capsys.readouterr().err


def test_a_baseline_run_resumed_as_another_method_says_which_it_is(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    assert (
        main(
            [
                "train",
                "calc",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "b"),
                "--steps",
                "1",
                "--set",
                "train.batch_size=2",
                "--set",
                "optim.lr=5e-4",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "finished at step 1/1" in capsys.readouterr().out
    # a run resumed with the wrong method says which it is
    assert main(["train", "--out", str(tmp_path / "b"), "--resume"]) == 2
    assert "is a calc run, not a fdnet run; resume it with `fdnet train calc" in capsys.readouterr().err
    assert main(["train", "netvlad", "--out", str(tmp_path / "b"), "--resume"]) == 2
    assert "not a netvlad run" in capsys.readouterr().err


def test_fdnet_steps_leave_the_joint_stage_the_rest(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    assert main(_tiny_train(data, tmp_path / "a", "--steps", "7")) == 0  # tiny: 3 + 2 pretraining steps
    assert "finished at step 7/7" in capsys.readouterr().out
    assert main(_tiny_train(data, tmp_path / "b", "--steps", "4")) == 2
    assert "pretraining stages alone take 5 steps" in capsys.readouterr().err


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="checks the message on a machine without a GPU")
@pytest.mark.parametrize("method", ["fdnet", "calc", "netvlad"])
def test_a_gpu_that_is_not_there_is_one_line_naming_runtime_device(tmp_path, capsys, method):
    data = _dataset(tmp_path / "data")
    assert (
        main(
            ["train", method, "--data", str(data), "--preset", "tiny", "--out", str(tmp_path / "r"), "--device", "cuda"]
        )
        == 2
    )
    assert "runtime.device cuda: no CUDA GPU is available here" in capsys.readouterr().err
    from fdnet import runs

    assert not runs.is_run(tmp_path / "r")


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("method", ["calc", "netvlad"])
def test_baselines_train_on_a_gpu(tmp_path, capsys, method):
    from fdnet import runs

    data = _dataset(tmp_path / "data")
    assert (
        main(
            [
                "train",
                method,
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "r"),
                "--device",
                "cuda",
                "--steps",
                "2",
                "--set",
                "train.batch_size=2",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "on cuda" in capsys.readouterr().err
    assert runs.load_training_state(tmp_path / "r")["step"] == 2


def test_a_baselines_shared_settings_have_one_path(tmp_path, capsys):
    from fdnet.methods.calc.config import CALCRunConfig
    from fdnet.runs import load_config

    data = _dataset(tmp_path / "data")
    assert (
        main(
            [
                "train",
                "calc",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "bad"),
                "--steps",
                "1",
                "--set",
                "train.lr=5e-4",
                "--no-progress",
            ]
        )
        == 2
    )
    assert "override train.lr: unknown setting 'lr'" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    assert (
        main(
            [
                "train",
                "calc",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(tmp_path / "r"),
                "--steps",
                "1",
                "--set",
                "train.batch_size=2",
                "--set",
                "optim.lr=5e-4",
                "--no-progress",
            ]
        )
        == 0
    )
    assert load_config(tmp_path / "r", CALCRunConfig).optim.lr == 5e-4
