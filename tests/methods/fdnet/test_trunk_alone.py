"""`trunk`: the frozen map FDNet reads, alone; with an FDNet run, that run's block and size."""

import numpy as np
import pytest

from fdnet import runs
from fdnet.config import replace_dotted
from fdnet.descriptors import create
from fdnet.errors import ConfigError
from fdnet.methods.fdnet.config import preset
from fdnet.methods.fdnet.model import FDNet


def _run(tmp_path, **model):
    config = replace_dotted(preset("tiny"), {f"model.{k}": v for k, v in model.items()})
    runs.save_weights(tmp_path / "run", FDNet(config.model).named_parts(), config)
    return tmp_path / "run"


def test_default_is_the_cpu_presets_map_unprojected():
    trunk = create("trunk", bf16=False)
    assert trunk.input_size == (128, 256) and trunk.dim == 80 * 8 * 16
    images = np.random.default_rng(0).random((2, 128, 256, 3), dtype=np.float32)
    vectors = trunk.describe(images)
    assert vectors.shape == (2, trunk.dim)
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
    # the same map conv3 computes, without the random projection
    conv3 = create("conv3", dim=0, input_size=[128, 256], bf16=False)
    np.testing.assert_allclose(vectors, conv3.describe(images), atol=1e-5)


def test_with_an_fdnet_run_it_reads_what_the_run_reads(tmp_path):
    run = _run(tmp_path, backbone="efficientnet-lite0", backbone_block=4, input_size=[32, 64], widths=[16])
    trunk = create("trunk", checkpoint=str(run))
    assert trunk.input_size == (32, 64) and trunk.dim == 40 * 4 * 8
    assert trunk.settings()["checkpoint"] == str(run)


def test_a_pixel_run_has_no_trunk(tmp_path):
    with pytest.raises(ConfigError, match="no trunk"):
        create("trunk", checkpoint=str(_run(tmp_path)))
