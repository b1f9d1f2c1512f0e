"""CALC: architecture as the original, HOG targets, warps, training, checkpoints, real data."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from PIL import Image

from fdnet import runs
from fdnet.config import replace_dotted
from fdnet.descriptors.base import describe_paths
from fdnet.errors import ConfigError, DataError
from fdnet.methods.calc import config as calc_config
from fdnet.methods.calc import model as calc
from fdnet.methods.calc.descriptor import CALCDescriptor
from fdnet.methods.calc.training import train

from conftest import require_shared


def train_calc(config, run_dir, resume=False, **kwargs):
    return train(config, run_dir, resume=resume, progress=False, **kwargs)


def make_route(root, frames=12, size=(48, 64), seed=0):
    """Two conditions of the same smooth random 'places' (the second darker and noisier)."""
    rng = np.random.default_rng(seed)
    for name in ("bright", "dark"):
        (root / name).mkdir(parents=True)
    for i in range(frames):
        coarse = rng.random((6, 8))
        place = np.kron(coarse, np.ones((size[0] // 6, size[1] // 8)))
        dark = np.clip(0.5 * place + 0.05 * rng.random(place.shape), 0, 1)
        for name, img in (("bright", place), ("dark", dark)):
            Image.fromarray((img * 255).astype(np.uint8)).convert("RGB").save(root / name / f"{i:04d}.png")
    return root


def tiny(root, steps=4, **train):
    config = calc_config.tiny_config()
    config.data.root = str(root)
    overrides = {"train.steps": steps, **{_path(config, k): v for k, v in train.items()}}
    return replace_dotted(config, overrides)


def _path(config, key: str) -> str:
    """Where a setting given by name lives: the shared ``optim``/``runtime`` sections, else ``train``."""
    section = next((s for s in ("optim", "runtime") if hasattr(getattr(config, s), key)), "train")
    return f"{section}.{key}"


def test_original_dimensions():
    # 120x160 grey input -> 4x14x19 = 1064-d bottleneck; HOG target 3648 values (the original's)
    model = calc_config.CALCModelConfig()
    assert calc.hog_length(model) == 3648
    net = calc.build_network(model)
    assert net.descriptor_dim == 1064
    assert net(torch.zeros(2, 1, 120, 160)).shape == (2, 3648)


def test_perspective_warp_only_zooms_in(rng):
    flat = np.full((60, 80), 200, np.uint8)
    warped = calc.random_perspective_warp(flat, rng)
    # zoom-in: every output pixel comes from inside the image, so no black border appears
    assert warped.shape == flat.shape and warped[1:-1, 1:-1].min() >= 199
    ramp = np.tile(np.arange(80, dtype=np.uint8) * 3, (60, 1))
    assert not np.array_equal(calc.random_perspective_warp(ramp, rng), ramp)


def test_train_describe_resume(tmp_path):
    route = make_route(tmp_path / "route")
    summary = train_calc(tiny(route, steps=4), tmp_path / "run")
    assert summary["status"] == "finished" and summary["step"] == 4
    losses = [float(r["loss"]) for r in csv.DictReader((tmp_path / "run" / "log.csv").open())]
    assert losses and np.isfinite(losses).all()
    desc = CALCDescriptor(checkpoint=tmp_path / "run", bf16=False)
    assert desc.input_size == (60, 80) and desc.step == 4
    paths = sorted((route / "bright").glob("*.png"))
    vectors = describe_paths(desc, paths)
    assert vectors.shape == (12, desc.dim) and vectors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)

    # resuming 2 + 2 steps gives the same weights as 4 steps in one go
    train_calc(tiny(route, steps=2, checkpoint_every=2), tmp_path / "split")
    with pytest.raises(ConfigError, match="train.steps: saved 2, requested 4.*--override"):
        train_calc(tiny(route, steps=4, checkpoint_every=2), tmp_path / "split", resume=True)
    train_calc(tiny(route, steps=4, checkpoint_every=2), tmp_path / "split", resume=True, override=True)
    assert runs.read_changes(tmp_path / "split")[0]["step"] == 2
    again = CALCDescriptor(checkpoint=tmp_path / "split", bf16=False)
    for (name, a), (_, b) in zip(desc.network.state_dict().items(), again.network.state_dict().items()):
        torch.testing.assert_close(a, b, msg=name)


def test_training_moves_the_encoder(tmp_path):
    """The reconstruction gradient reaches every encoder layer and bottleneck units stay alive.
    (A sanity check only: the stall seen with the reference N(0, 0.01) decoder init appeared after
    dozens of full-size steps, too slow to reproduce in a unit test.)"""
    route = make_route(tmp_path / "route")
    config = tiny(route, steps=8)
    torch.manual_seed(config.runtime.seed)
    initial = calc.build_network(config.model).state_dict()
    train_calc(config, tmp_path / "run")
    trained = CALCDescriptor(checkpoint=tmp_path / "run", bf16=False).network.state_dict()
    for name in ("encoder.0.weight", "encoder.4.weight", "encoder.8.weight"):
        assert (trained[name] - initial[name]).abs().max() > 1e-3, name
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert float(rows[-1]["active_units"]) > 0  # share of active bottleneck units


def test_training_errors(tmp_path):
    route = make_route(tmp_path / "route", frames=3)
    with pytest.raises(DataError, match="fewer than one batch"):
        train_calc(tiny(route, batch_size=32), tmp_path / "run")
    train_calc(tiny(route, steps=1, batch_size=2), tmp_path / "run")
    with pytest.raises(ConfigError, match="already holds a run"):
        train_calc(tiny(route, steps=1, batch_size=2), tmp_path / "run")
    changed = replace_dotted(tiny(route, steps=2, batch_size=2), {"model.channels": [8, 8, 4]})
    with pytest.raises(ConfigError, match="model.channels"):
        train_calc(changed, tmp_path / "run", resume=True)
    with pytest.raises(ConfigError, match="optim.lr"):
        train_calc(tiny(route, lr=float("nan")), tmp_path / "nan")
    with pytest.raises(ConfigError, match="no training data"):
        train_calc(calc_config.tiny_config(), tmp_path / "other")


def test_descriptor_checkpoint_errors(tmp_path):
    with pytest.raises(ConfigError, match="--checkpoint"):
        CALCDescriptor()
    with pytest.raises(ConfigError, match="run directory not found"):
        CALCDescriptor(checkpoint=tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="not a run directory"):
        CALCDescriptor(checkpoint=tmp_path / "empty")
    from fdnet.methods.netvlad.config import tiny_config as netvlad_tiny
    from fdnet.methods.netvlad.model import build_network as netvlad_network

    other = tmp_path / "netvlad_run"
    runs.save_weights(other, {"netvlad": netvlad_network(netvlad_tiny().model, pretrained=False)}, netvlad_tiny())
    with pytest.raises(ConfigError, match="'netvlad' run, not a calc run"):
        CALCDescriptor(checkpoint=other)


@pytest.mark.shared_data
@pytest.mark.slow
def test_gardens_point_above_chance(tmp_path):
    """Trained a few dozen steps on other frames, CALC matches day_left -> day_right far above chance."""
    from fdnet.data.dataset import RouteDataset
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    config = tiny(root, steps=30)
    config.data.conditions = ("day_left", "day_right")
    config.data.frames = "0:40"
    train_calc(config, tmp_path / "run")
    desc = CALCDescriptor(checkpoint=tmp_path / "run")
    route = RouteDataset.from_folder(root, ["day_left", "day_right"]).frames(100, 140)
    refs = describe_paths(desc, route["day_right"].paths)
    queries = describe_paths(desc, route["day_left"].paths)
    gt = GroundTruth.aligned(40, 40, tolerance=2)
    retrieved, _ = top_k(queries, refs, k=1)
    recall_at_1 = gt.correct_mask(retrieved)[:, 0].mean()
    chance = 5 / 40
    assert recall_at_1 > 2 * chance, recall_at_1
