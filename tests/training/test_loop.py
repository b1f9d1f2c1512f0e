"""The shared training loop, driven by FDNet's tiny preset: finite losses, bit-exact
checkpoints, exact resume, resume with changed settings, the run lock, validation and best/,
bad input. (CALC and NetVLAD on the same loop: tests/methods/calc, tests/methods/netvlad.)"""

import csv
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet import runs
from fdnet.config import replace_dotted
from fdnet.errors import ConfigError, DataError
from fdnet.methods.fdnet.config import preset, validate
from fdnet.methods.fdnet.model import FDNet
from fdnet.methods.fdnet.training import FDNetTraining, load_training_images
from fdnet.runs import load_training_state, load_weights
from fdnet.training.data import load_validation_images
from fdnet.training.loop import Trainer


def make_dataset(root, conditions=("summer", "winter"), n=10, size=(16, 32)):
    rng = np.random.default_rng(0)
    base = rng.random((n, size[0], size[1]))
    for k, name in enumerate(conditions):
        (root / name).mkdir(parents=True)
        for i in range(n):
            grey = np.clip(base[i] * (0.5 + 0.4 * k) + 0.05 * rng.random(size), 0, 1)
            Image.fromarray((grey * 255).astype(np.uint8)).convert("RGB").save(root / name / f"{i:04d}.png")
    return root


def _config(data_root, **overrides):
    return replace_dotted(preset("tiny"), {"data.root": str(data_root), **overrides})


def _load(config, conditions=(), frames="", batch=None):
    overrides = {"data.conditions": list(conditions), "data.frames": frames}
    if batch is not None:
        overrides["data.batch_per_domain"] = batch
    return load_training_images(replace_dotted(config, overrides))


def _trainer(tmp_path, run="run", resume=False, override=False, **overrides):
    data_root = tmp_path / "data"
    if not data_root.exists():
        make_dataset(data_root)
    config = _config(data_root, **overrides)
    method = FDNetTraining(config, load_training_images(config))
    validation = load_validation_images(data_root, config.validation, config.model.input_size)
    trainer = Trainer(
        method, tmp_path / run, validation=validation, resume=resume, override=override, tensorboard=False
    )
    trainer.config, trainer.model = config, method.model  # shorthand for the tests below
    return trainer


def test_tiny_trains_with_finite_losses_and_round_trips(tmp_path):
    trainer = _trainer(tmp_path)
    summary = trainer.fit(progress=False)
    assert summary["status"] == "finished" and summary["step"] == trainer.config.total_steps
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert {r["stage"] for r in rows} == {"autoencoder", "critic", "joint"}
    for r in rows:
        for key in ("reconstruction", "appearance", "encoder_adversarial", "critic", "wasserstein"):
            if r[key]:
                assert math.isfinite(float(r[key])), (key, r)
    fresh = FDNet(trainer.config.model)
    load_weights(tmp_path / "run", fresh.named_parts())
    for (name, a), b in zip(trainer.model.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), name
    assert load_training_state(tmp_path / "run")["step"] == trainer.config.total_steps
    # the weights at the end of each stage are kept, each loadable on its own, at its last step
    schedule = trainer.config.schedule
    ends = {
        "autoencoder": schedule.pretrain_autoencoder_steps,
        "critic": schedule.pretrain_autoencoder_steps + schedule.pretrain_critic_steps,
        "joint": trainer.config.total_steps,
    }
    for stage, step in ends.items():
        folder = tmp_path / "run" / "stages" / stage
        assert runs.is_run(folder), stage
        assert runs.latest_checkpoint(folder).name == f"step-{step:09d}", stage
    final = FDNet(trainer.config.model)
    load_weights(tmp_path / "run" / "stages" / "joint", final.named_parts())
    assert all(torch.equal(a, b) for a, b in zip(trainer.model.state_dict().values(), final.state_dict().values()))


# the tiny preset as is, and with a frozen trunk (whose maps the trainer caches)
TRUNK = {
    "model.backbone": "efficientnet-lite0",
    "model.backbone_block": 4,
    "model.input_size": (32, 64),
    "model.widths": (16,),
}


@pytest.mark.parametrize("model", [{}, TRUNK], ids=["pixels", "trunk"])
def test_resume_continues_at_the_right_step_and_matches_one_run(tmp_path, model):
    whole = _trainer(tmp_path, "whole", **model)
    whole.fit(progress=False)

    half = _trainer(tmp_path, "half", **model)
    half.settings.total_steps = 6  # as if interrupted inside the joint stage (same settings)
    half.fit(progress=False)
    assert half.step == 6
    # resume picks up at step 6 and runs to the end
    resumed = _trainer(tmp_path, "half", resume=True, **model)
    assert resumed.step == 6
    resumed.fit(progress=False)
    assert resumed.step == whole.step == 8
    for (name, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(a.float(), b.float(), atol=1e-6), name
    steps = [int(r["step"]) for r in csv.DictReader((tmp_path / "half" / "log.csv").open())]
    assert steps == sorted(set(steps)) and steps[-1] == 8


def test_time_limit_stops_with_a_checkpoint(tmp_path):
    trainer = _trainer(tmp_path)
    summary = trainer.fit(max_minutes=0.0, progress=False)
    assert summary["status"] == "time limit" and summary["step"] == 1
    assert load_training_state(tmp_path / "run")["step"] == 1


def test_existing_run_needs_resume_and_matching_model(tmp_path):
    _trainer(tmp_path).fit(max_minutes=0.0, progress=False)
    with pytest.raises(ConfigError, match="--resume"):
        _trainer(tmp_path)
    with pytest.raises(ConfigError, match="model.vector_length: saved 16, requested 32"):
        _trainer(tmp_path, resume=True, **{"model.vector_length": 32})
    # an architecture change cannot be forced: the weights do not fit
    with pytest.raises(ConfigError, match="shape|does not match"):
        _trainer(tmp_path, resume=True, override=True, **{"model.vector_length": 32})


def test_resume_refuses_changed_settings_unless_override_and_records_them(tmp_path):
    _trainer(tmp_path, **{"schedule.joint_steps": 1}).fit(progress=False)
    with pytest.raises(ConfigError, match=r"optim.lr: saved 0.0001, requested 0.0002.*--override"):
        _trainer(tmp_path, resume=True, **{"schedule.joint_steps": 1, "optim.lr": 2e-4})
    assert runs.read_changes(tmp_path / "run") == []
    trainer = _trainer(tmp_path, resume=True, override=True, **{"schedule.joint_steps": 3, "optim.lr": 2e-4})
    trainer.fit(progress=False)
    changes = runs.read_changes(tmp_path / "run")
    assert len(changes) == 1 and changes[0]["step"] == 6
    assert any("optim.lr" in d for d in changes[0]["changes"])
    assert any("schedule.joint_steps" in d for d in changes[0]["changes"])
    # the run's config now says what the rest of the run used
    assert runs.load_config(tmp_path / "run", type(trainer.config)).optim.lr == 2e-4


def test_a_second_training_on_a_locked_run_directory_stops_naming_the_holder(tmp_path):
    import os

    from fdnet.methods.fdnet.training import train

    make_dataset(tmp_path / "data")
    config = _config(tmp_path / "data")
    with runs.RunLock(tmp_path / "run", command="fdnet train (other)"):
        with pytest.raises(ConfigError, match=f"in use by process {os.getpid()}"):
            train(config, tmp_path / "run", progress=False)
    assert not runs.is_run(tmp_path / "run")
    train(config, tmp_path / "run", progress=False)  # lock released: the run goes ahead
    assert runs.is_run(tmp_path / "run")


def test_a_checkpoint_write_that_fails_keeps_the_previous_one_and_the_run_resumes(tmp_path, monkeypatch):
    import errno

    import fdnet.runs as runs_module

    trainer = _trainer(tmp_path, **{"runtime.checkpoint_every": 2})
    real = runs_module.save_checkpoint

    def disk_full_at_step_6(run_dir, modules, config, optimizers=None, state=None, **kwargs):
        if state["step"] == 6:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(run_dir, modules, config, optimizers=optimizers, state=state, **kwargs)

    monkeypatch.setattr(runs_module, "save_checkpoint", disk_full_at_step_6)
    with pytest.raises(ConfigError, match="step 6.*No space left.*--resume") as failure:
        trainer.fit(progress=False)
    assert isinstance(failure.value, OSError) and failure.value.errno == errno.ENOSPC  # an OutputError
    monkeypatch.setattr(runs_module, "save_checkpoint", real)  # space returns
    assert load_training_state(tmp_path / "run")["step"] == 4
    resumed = _trainer(tmp_path, resume=True, **{"runtime.checkpoint_every": 2})
    assert resumed.step == 4
    assert resumed.fit(progress=False)["step"] == 8


def test_best_checkpoint_from_validation(tmp_path):
    trainer = _trainer(
        tmp_path, **{"validation.reference": "summer", "validation.query": "winter", "validation.every": 2}
    )
    summary = trainer.fit(progress=False)
    assert summary["best_step"] > 0
    assert runs.is_run(tmp_path / "run" / "best")
    assert "recall@1" in (tmp_path / "run" / "best" / "validation.yaml").read_text()


def test_bad_input_fails_before_training(tmp_path):
    make_dataset(tmp_path / "one", conditions=("summer",))
    with pytest.raises(DataError, match="at least 2 conditions"):
        _load(_config(tmp_path / "one"))
    make_dataset(tmp_path / "two")
    with pytest.raises(DataError, match="data.batch_per_domain = 4"):
        _load(_config(tmp_path / "two"), frames="0:3", batch=4)
    with pytest.raises(DataError, match="autumn: condition folder not found"):
        _load(_config(tmp_path / "two"), conditions=("summer", "autumn"))
    for bad in ("nan", "-1e-4", "inf", "0"):
        with pytest.raises(ConfigError, match="optim.lr"):
            validate(replace_dotted(preset("tiny"), {"optim.lr": bad}))
    with pytest.raises(ConfigError, match="height 18"):
        validate(replace_dotted(preset("tiny"), {"model.input_size": [18, 32]}))
    with pytest.raises(ConfigError, match="unknown preset"):
        preset("huge")


def test_best_checkpoint_breaks_recall_ties_by_auc(tmp_path, monkeypatch):
    import fdnet.training.loop as trainer_module

    trainer = _trainer(tmp_path)
    scores = iter([(0.5, 0.2), (0.9, 0.3), (0.9, 0.6), (0.9, 0.4), (0.8, 0.9)])

    def fake_metrics(*args, **kwargs):
        r1, auc = next(scores)
        return {"recall@1": r1, "recall@5": r1, "recall@100p": 0.0, "auc": auc}

    monkeypatch.setattr(trainer_module, "validation_metrics", fake_metrics)
    trainer.validation = SimpleNamespace(description="fake")
    for step in range(5):
        trainer.step = step
        trainer.validate_now()
    assert trainer.best == {"step": 2, "recall@1": 0.9, "auc": 0.6}
    assert "step: 2" in (tmp_path / "run" / "best" / "validation.yaml").read_text()


def test_algorithm1_batch_use_samples_one_batch_per_joint_step(tmp_path):
    trainer = _trainer(
        tmp_path,
        **{
            "schedule.one_batch_per_step": True,
            "loss.reconstruction_reduction": "sum",
            "loss.triplet_vectors": "l2",
            "model.critic_input": "raw",
        },
    )
    method = trainer.method
    drawn = []
    real = method.sampler.sample

    def counting():
        drawn.append(1)
        return real()

    method.sampler.sample = counting
    for step in range(trainer.settings.total_steps):
        before = len(drawn)
        numbers = method.train_step(step)
        assert all(math.isfinite(v) for v in numbers.values())
        if method.stage(step) == "joint":
            assert len(drawn) - before == 1, "Algorithm 1: one mini-batch X_b per joint step"
            assert {"critic", "encoder_adversarial", "reconstruction", "appearance"} <= set(numbers)


def test_a_full_disk_before_the_first_checkpoint_says_to_run_again_not_to_resume(tmp_path, monkeypatch):
    import errno

    import fdnet.runs as runs_module

    trainer = _trainer(tmp_path, **{"runtime.checkpoint_every": 2})

    def disk_full(run_dir, modules, config, optimizers=None, state=None, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(runs_module, "save_checkpoint", disk_full)
    with pytest.raises(ConfigError, match="no checkpoint was written before it.*run the same command again") as failure:
        trainer.fit(progress=False)
    assert "--resume" not in str(failure.value) and failure.value.errno == errno.ENOSPC
