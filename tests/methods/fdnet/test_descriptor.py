"""FDNet behind the descriptor interface: create("fdnet", checkpoint=RUN_DIR) and fdnet.load."""

import numpy as np
import pytest
import torch

import fdnet
from fdnet.descriptors import create
from fdnet.errors import DataError, NotAvailableError
from fdnet.methods.fdnet.config import preset
from fdnet.methods.fdnet.model import FDNet
from fdnet.runs import save_checkpoint


@pytest.fixture
def run_dir(tmp_path):
    config = preset("tiny")
    torch.manual_seed(0)
    model = FDNet(config.model)
    save_checkpoint(tmp_path / "run", model.named_parts(), config, state={"step": 3})
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
    np.testing.assert_allclose(
        fdnet.load(run_dir).describe(images), create("fdnet", checkpoint=run_dir).describe(images)
    )


def test_fdnet_load_refuses_another_methods_run_naming_it(run_dir, monkeypatch):
    """fdnet.load goes through the check every command's descriptor goes through: a run that
    records another method is refused naming it (it failed on the run config's keys)."""
    import fdnet.runs
    from fdnet.errors import ConfigError

    monkeypatch.setattr(fdnet.runs, "recorded_method", lambda path: "calc")  # what a CALC run records
    with pytest.raises(ConfigError, match="a run of `fdnet train calc`, not of fdnet"):
        fdnet.load(run_dir)


def test_errors(run_dir, rng):
    with pytest.raises(NotAvailableError, match="--checkpoint"):
        create("fdnet")
    with pytest.raises(DataError, match="16x32"):
        create("fdnet", checkpoint=run_dir).describe(rng.random((1, 32, 32, 3)).astype(np.float32))


def test_a_run_directory_means_its_best_weights_and_says_so(run_dir, rng, caplog):
    """A run that validated keeps its best weights in best/: --checkpoint RUN uses them (and
    says which step), not the last step; best/ or a step folder given directly means itself."""
    from fdnet.runs import save_weights

    config = preset("tiny")
    torch.manual_seed(1)
    best_model = FDNet(config.model)
    save_weights(run_dir / "best", best_model.named_parts(), config, step=2)
    images = rng.random((2, 16, 32, 3)).astype(np.float32)
    with caplog.at_level("INFO"):
        d = create("fdnet", checkpoint=str(run_dir))
    assert d.step == 2 and "using its best-validating weights, best/ (step 2)" in caplog.text
    np.testing.assert_allclose(d.describe(images), create("fdnet", checkpoint=run_dir / "best").describe(images))
    last = next((run_dir / "checkpoints").iterdir())
    assert create("fdnet", checkpoint=last).step == 3
    assert not np.allclose(create("fdnet", checkpoint=last).describe(images), d.describe(images))
