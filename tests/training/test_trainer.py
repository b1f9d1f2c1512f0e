"""The tiny preset end to end: finite losses, bit-exact checkpoints, exact resume, bad input."""

import csv
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet.config import replace_dotted
from fdnet.errors import ConfigError, DataError
from fdnet.models import FDNet
from fdnet.training.checkpoint import load_training_state, load_weights
from fdnet.training.config import preset, validate
from fdnet.training.trainer import Trainer, load_training_images, load_validation_images


def make_dataset(root, conditions=("summer", "winter"), n=10, size=(16, 32)):
    rng = np.random.default_rng(0)
    base = rng.random((n, size[0], size[1]))
    for k, name in enumerate(conditions):
        (root / name).mkdir(parents=True)
        for i in range(n):
            grey = np.clip(base[i] * (0.5 + 0.4 * k) + 0.05 * rng.random(size), 0, 1)
            Image.fromarray((grey * 255).astype(np.uint8)).convert("RGB").save(root / name / f"{i:04d}.png")
    return root


def _trainer(tmp_path, run="run", resume=False, **overrides):
    data_root = tmp_path / "data"
    if not data_root.exists():
        make_dataset(data_root)
    config = replace_dotted(preset("tiny"), overrides) if overrides else preset("tiny")
    data = load_training_images(data_root, (), "", config.model.input_size, config.data.batch_per_domain)
    return Trainer(config, data, tmp_path / run, validation=load_validation_images(data_root, config),
                   resume=resume, tensorboard=False)


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


# the tiny preset as is, and with a frozen trunk (whose maps the trainer caches)
TRUNK = {"model.backbone": "efficientnet-lite0", "model.backbone_block": 4, "model.input_size": (32, 64),
         "model.widths": (16,)}


@pytest.mark.parametrize("model", [{}, TRUNK], ids=["pixels", "trunk"])
def test_resume_continues_at_the_right_step_and_matches_one_run(tmp_path, model):
    whole = _trainer(tmp_path, "whole", **model)
    whole.fit(progress=False)

    half = _trainer(tmp_path, "half", **model, **{"schedule.joint_steps": 1})  # stops inside the joint stage
    half.fit(progress=False)
    assert half.step == 6
    # same model settings, longer schedule: resume picks up at step 6 and runs to the end
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


def test_best_checkpoint_from_validation(tmp_path):
    trainer = _trainer(tmp_path, **{"validation.reference": "summer", "validation.query": "winter",
                                    "validation.every": 2})
    summary = trainer.fit(progress=False)
    assert summary["best_step"] > 0
    assert (tmp_path / "run" / "best" / "model.safetensors").exists()
    assert "recall@1" in (tmp_path / "run" / "best" / "validation.yaml").read_text()


def test_bad_input_fails_before_training(tmp_path):
    make_dataset(tmp_path / "one", conditions=("summer",))
    with pytest.raises(DataError, match="at least two conditions"):
        load_training_images(tmp_path / "one", (), "", (16, 32), 2)
    make_dataset(tmp_path / "two")
    with pytest.raises(DataError, match="fewer than data.batch_per_domain = 4"):
        load_training_images(tmp_path / "two", (), "0:3", (16, 32), 4)
    with pytest.raises(DataError, match="autumn: condition folder not found"):
        load_training_images(tmp_path / "two", ("summer", "autumn"), "", (16, 32), 2)
    with pytest.raises(ConfigError, match="height 18"):
        validate(replace_dotted(preset("tiny"), {"model.input_size": [18, 32]}))
    with pytest.raises(ConfigError, match="unknown preset"):
        preset("huge")


def test_best_checkpoint_breaks_recall_ties_by_auc(tmp_path, monkeypatch):
    import fdnet.training.trainer as trainer_module

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
