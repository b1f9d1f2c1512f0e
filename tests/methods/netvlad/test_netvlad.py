"""NetVLAD: the layer against the reference formula, k-means/alpha init, training, checkpoints,
errors, and real data."""

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
from fdnet.methods.netvlad import config as netvlad_config
from fdnet.methods.netvlad import model as netvlad
from fdnet.methods.netvlad.descriptor import NetVLADDescriptor
from fdnet.methods.netvlad.training import train

from conftest import require_shared


def train_netvlad(config, run_dir, resume=False, **kwargs):
    return train(config, run_dir, resume=resume, progress=False, **kwargs)


def make_route(root, frames=12, size=(48, 64), seed=0):
    """Two conditions of the same smooth random 'places' (the second darker and noisier)."""
    rng = np.random.default_rng(seed)
    for name in ("bright", "dark"):
        (root / name).mkdir(parents=True)
    for i in range(frames):
        place = np.kron(rng.random((6, 8, 3)), np.ones((size[0] // 6, size[1] // 8, 1)))
        dark = np.clip(0.5 * place + 0.05 * rng.random(place.shape), 0, 1)
        for name, img in (("bright", place), ("dark", dark)):
            Image.fromarray((img * 255).astype(np.uint8)).save(root / name / f"{i:04d}.png")
    return root


def tiny(root, steps=4, tolerance=0, **train):
    config = netvlad_config.tiny_config()
    config.data.root = str(root)
    config.data.tolerance = tolerance
    return replace_dotted(config, {"train.steps": steps, **{_path(config, k): v for k, v in train.items()}})


def _path(config, key: str) -> str:
    """Where a setting given by name lives: the shared ``optim``/``runtime`` sections, else ``train``."""
    section = next((s for s in ("optim", "runtime") if hasattr(getattr(config, s), key)), "train")
    return f"{section}.{key}"


def test_vlad_layer_matches_reference_formula():
    """The batched layer equals the original's per-cluster loop: soft-assign, residual sums,
    intra-normalisation, final L2."""
    torch.manual_seed(0)
    model = netvlad_config.NetVLADModelConfig(clusters=5, frozen_block=7, last_block=8)
    net = netvlad.build_network(model, pretrained=False)
    layer = net.vlad
    x = torch.randn(3, 112, 4, 6)
    got = layer(x)
    xn = torch.nn.functional.normalize(x, dim=1).flatten(2)  # (N, C, P)
    soft = torch.softmax(torch.einsum("kc,ncp->nkp", layer.assign.weight[:, :, 0, 0], xn), dim=1)
    expected = torch.zeros(3, 5, 112)
    for k in range(5):
        residual = xn - layer.centroids[k][None, :, None]
        expected[:, k] = (residual * soft[:, k : k + 1]).sum(-1)
    expected = torch.nn.functional.normalize(expected, dim=2).flatten(1)
    expected = torch.nn.functional.normalize(expected, dim=1)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-4)
    assert got.shape == (3, 5 * 112) and net.descriptor_dim == 560


def test_alpha_initialisation(rng):
    net = netvlad.build_network(
        netvlad_config.NetVLADModelConfig(clusters=4, frozen_block=7, last_block=8), pretrained=False
    )
    centroids = rng.normal(size=(4, 112)).astype(np.float32)
    local = rng.normal(size=(200, 112)).astype(np.float32)
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    alpha = net.vlad.initialise(centroids, local)
    unit = centroids / np.linalg.norm(centroids, axis=1, keepdims=True)
    dots = np.sort(unit @ local.T, axis=0)[::-1]
    assert alpha == pytest.approx(-np.log(0.01) / np.mean(dots[0] - dots[1]), rel=1e-6)
    np.testing.assert_allclose(net.vlad.assign.weight[:, :, 0, 0].detach().numpy(), alpha * unit, rtol=1e-5)
    np.testing.assert_allclose(net.vlad.centroids.detach().numpy(), centroids)


def test_train_describe_resume(tmp_path):
    route = make_route(tmp_path / "route")
    summary = train_netvlad(tiny(route, steps=4), tmp_path / "run")
    assert summary["status"] == "finished" and summary["step"] == 4
    losses = [float(r["loss"]) for r in csv.DictReader((tmp_path / "run" / "log.csv").open())]
    assert losses and np.isfinite(losses).all()
    desc = NetVLADDescriptor(checkpoint=tmp_path / "run", bf16=False)
    assert desc.dim == 8 * 112 and desc.input_size == (64, 112)
    vectors = describe_paths(desc, sorted((route / "dark").glob("*.png")))
    assert vectors.shape == (12, desc.dim)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)

    train_netvlad(tiny(route, steps=2, checkpoint_every=2), tmp_path / "split")
    train_netvlad(tiny(route, steps=4, checkpoint_every=2), tmp_path / "split", resume=True, override=True)
    again = NetVLADDescriptor(checkpoint=tmp_path / "split", bf16=False)
    for (name, a), (_, b) in zip(desc.network.state_dict().items(), again.network.state_dict().items()):
        torch.testing.assert_close(a, b, msg=name)


def test_pca_whitening(tmp_path):
    route = make_route(tmp_path / "route")
    config = replace_dotted(tiny(route, steps=2), {"model.pca_dim": 6})
    train_netvlad(config, tmp_path / "run")
    desc = NetVLADDescriptor(checkpoint=tmp_path / "run", bf16=False)
    vectors = describe_paths(desc, sorted((route / "bright").glob("*.png")))
    assert vectors.shape == (12, 6)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
    too_long = replace_dotted(tiny(route, steps=2), {"model.pca_dim": 500})
    with pytest.raises(ConfigError, match="pca_dim 500 needs more training images"):
        train_netvlad(too_long, tmp_path / "run2")


def test_training_errors(tmp_path):
    route = make_route(tmp_path / "route")
    one = tiny(route)
    one.data.conditions = ("bright",)
    with pytest.raises(DataError, match="at least 2 conditions"):
        train_netvlad(one, tmp_path / "a")
    with pytest.raises(DataError, match="has no negative"):
        train_netvlad(tiny(route, negative_distance=20), tmp_path / "b")
    with pytest.raises(ConfigError, match="must be >= the tolerance"):
        train_netvlad(tiny(route, tolerance=5, negative_distance=2), tmp_path / "c")
    with pytest.raises(ConfigError, match="frozen_block <= last_block"):
        train_netvlad(replace_dotted(tiny(route), {"model.last_block": 6}), tmp_path / "d")
    (route / "dark" / "0000.png").unlink()
    with pytest.raises(DataError, match="same frames in every training condition"):
        train_netvlad(tiny(route), tmp_path / "e")


def test_descriptor_checkpoint_errors(tmp_path):
    with pytest.raises(ConfigError, match="--checkpoint"):
        NetVLADDescriptor()
    from fdnet.methods.calc.config import tiny_config as calc_tiny
    from fdnet.methods.calc.model import build_network as calc_network

    calc_run = tmp_path / "calc_run"
    runs.save_weights(calc_run, {"calc": calc_network(calc_tiny().model)}, calc_tiny())
    with pytest.raises(ConfigError, match="'calc' run, not a netvlad run"):
        NetVLADDescriptor(checkpoint=calc_run)


@pytest.mark.shared_data
@pytest.mark.slow
def test_gardens_point_above_chance(tmp_path):
    """Trained briefly on other frames, NetVLAD matches day_left -> day_right far above chance."""
    from fdnet.data.dataset import RouteDataset
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.matching.similarity import top_k

    root = require_shared("gardens_point")
    config = tiny(root, steps=6, tolerance=2)
    config.data.conditions = ("day_left", "day_right")
    config.data.frames = "0:40"
    train_netvlad(config, tmp_path / "run")
    desc = NetVLADDescriptor(checkpoint=tmp_path / "run")
    route = RouteDataset.from_folder(root, ["day_left", "day_right"]).frames(100, 140)
    refs = describe_paths(desc, route["day_right"].paths)
    queries = describe_paths(desc, route["day_left"].paths)
    retrieved, _ = top_k(queries, refs, k=1)
    recall_at_1 = GroundTruth.aligned(40, 40, tolerance=2).correct_mask(retrieved)[:, 0].mean()
    assert recall_at_1 > 2 * 5 / 40, recall_at_1
