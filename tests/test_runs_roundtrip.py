"""Run directories: bit-exact round trip, resume state, clear errors on mismatch."""

from dataclasses import dataclass, field

import pytest
import torch

from fdnet.errors import ConfigError
from fdnet.runs import (
    check_config, load_config, load_training_state, load_weights, save_run,
)


@dataclass
class _Net:
    width: int = 4


@dataclass
class _Cfg:
    net: _Net = field(default_factory=_Net)
    lr: float = 1e-3


def _model(width=4):
    return torch.nn.Sequential(torch.nn.Linear(3, width), torch.nn.BatchNorm1d(width))


def test_round_trip_is_bit_exact(tmp_path):
    torch.manual_seed(0)
    model = _model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model(torch.randn(5, 3)).sum().backward()
    opt.step()
    rng = torch.get_rng_state()
    save_run(tmp_path, {"net": model}, _Cfg(), optimizers={"opt": opt}, state={"step": 7, "rng": rng})

    other = _model()
    other_opt = torch.optim.Adam(other.parameters(), lr=1e-3)
    meta = load_weights(tmp_path, {"net": other})
    assert meta["step"] == "7"
    for (k, a), (_, b) in zip(model.state_dict().items(), other.state_dict().items()):
        assert torch.equal(a, b), k
    state = load_training_state(tmp_path, {"opt": other_opt})
    assert state["step"] == 7
    assert torch.equal(state["rng"], rng)
    a = opt.state_dict()["state"][0]["exp_avg"]
    b = other_opt.state_dict()["state"][0]["exp_avg"]
    assert torch.equal(a, b)
    assert load_config(tmp_path, _Cfg) == _Cfg()


def test_shape_mismatch_is_a_config_error(tmp_path):
    save_run(tmp_path, {"net": _model(4)}, _Cfg())
    with pytest.raises(ConfigError, match="shape"):
        load_weights(tmp_path, {"net": _model(6)})
    with pytest.raises(ConfigError, match="no weights for module 'other'"):
        load_weights(tmp_path, {"other": _model(4)})
    with pytest.raises(ConfigError, match="cannot be resumed"):
        load_training_state(tmp_path)


def test_check_config_names_the_difference(tmp_path):
    with pytest.raises(ConfigError, match=r"net.width: saved 4, requested 8"):
        check_config(tmp_path, _Cfg(), _Cfg(net=_Net(width=8)), keys=["net.width"])
    check_config(tmp_path, _Cfg(), _Cfg(lr=0.1), keys=["net.width"])  # other keys ignored


def test_not_a_run_directory(tmp_path):
    with pytest.raises(ConfigError, match="run directory not found"):
        load_weights(tmp_path / "nope", {"net": _model()})
    with pytest.raises(ConfigError, match="not a run directory"):
        load_weights(tmp_path, {"net": _model()})
