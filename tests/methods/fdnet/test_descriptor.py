"""FDNet behind the descriptor interface: create("fdnet", checkpoint=RUN_DIR) and fdnet.load."""

import numpy as np
import pytest
import torch

import fdnet
from fdnet.descriptors import create
from fdnet.errors import DataError, NotAvailableError
from fdnet.methods.fdnet.model import FDNet
from fdnet.runs import save_run
from fdnet.methods.fdnet.config import preset


@pytest.fixture
def run_dir(tmp_path):
    config = preset("tiny")
    torch.manual_seed(0)
    model = FDNet(config.model)
    save_run(tmp_path / "run", model.named_parts(), config, state={"step": 3})
    return tmp_path / "run"


def test_describe_gives_unit_content_vectors(run_dir, rng):
    d = create("fdnet", checkpoint=str(run_dir))
    assert d.input_size == (16, 32) and d.dim == 16 and d.step == 3
    images = rng.random((5, 16, 32, 3)).astype(np.float32)
    v = d.describe(images)
    assert v.shape == (5, 16) and v.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(d.describe(images), v)  # eval mode: deterministic
    assert d.similarity(v, v).shape == (5, 5)
    assert d.describe_appearance(images).shape == (5, 16)


def test_fdnet_load_is_the_same_descriptor(run_dir, rng):
    images = rng.random((2, 16, 32, 3)).astype(np.float32)
    np.testing.assert_allclose(fdnet.load(run_dir).describe(images), create("fdnet", checkpoint=run_dir).describe(images))


def test_errors(run_dir, rng):
    with pytest.raises(NotAvailableError, match="--checkpoint"):
        create("fdnet")
    with pytest.raises(DataError, match="16x32"):
        create("fdnet", checkpoint=run_dir).describe(rng.random((1, 32, 32, 3)).astype(np.float32))
