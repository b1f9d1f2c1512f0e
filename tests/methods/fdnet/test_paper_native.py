"""The ``paper-native`` preset: the paper's recipe at Nordland's 32x64 for 2 CPU cores; it trains
with its own widths, bf16 and channels_last, and resumes exactly."""

from __future__ import annotations

import torch

from fdnet.config import replace_dotted
from fdnet.methods.fdnet.config import FDNetRunConfig, preset
from fdnet.methods.fdnet.model import FDNet
from fdnet.methods.fdnet.training import train
from fdnet.runs import load_config, load_training_state, load_weights
from tests.training.test_loop import make_dataset


def test_paper_native_is_the_paper_at_32x64_for_two_cores():
    native, paper = preset("paper-native"), preset("paper")
    assert tuple(native.model.input_size) == (32, 64)
    assert tuple(native.model.widths) == (64, 128, 256, 512)
    assert (native.runtime.bf16, native.runtime.channels_last, native.runtime.threads) == (True, True, 2)
    # everything else the paper's: schedule, Algorithm 1, optimiser, losses, batch, vector length, critic input
    assert native.schedule == paper.schedule and native.total_steps == 73000
    assert native.optim == paper.optim and native.loss == paper.loss and native.data == paper.data
    assert native.model.vector_length == 512 and native.model.critic_input == "raw"
    assert native.model.input_norm == paper.model.input_norm == "none"


def _weights(run) -> dict[str, torch.Tensor]:
    model = FDNet(load_config(run, FDNetRunConfig).model)
    load_weights(run, model.named_parts())
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_paper_native_trains_every_stage_and_resumes_exactly(tmp_path):
    data = make_dataset(tmp_path / "data", size=(32, 64))
    # the preset's input size, precision, memory format and losses; a few steps of each stage, and
    # a quarter of its widths (its 20M weights and Adam moments make each checkpoint ~240 MB)
    config = replace_dotted(
        preset("paper-native"),
        {
            "data.root": str(data),
            "schedule.pretrain_autoencoder_steps": 2,
            "schedule.pretrain_critic_steps": 2,
            "schedule.joint_steps": 2,
            "model.widths": [16, 32, 64, 128],
            "runtime.log_every": 1,
            "validation.reference": "summer",
            "validation.query": "winter",
            "validation.every": 3,
        },
    )
    whole = tmp_path / "whole"
    summary = train(config, whole, progress=False)
    assert summary["status"] == "finished" and summary["step"] == 6
    log = (whole / "log.csv").read_text().splitlines()
    assert [line.split(",")[1] for line in log[1:]] == ["autoencoder"] * 2 + ["critic"] * 2 + ["joint"] * 2
    assert load_config(whole, FDNetRunConfig).preset == "paper-native"

    stopped = tmp_path / "stopped"
    assert train(config, stopped, max_minutes=0.0, progress=False)["status"] == "time limit"
    assert load_training_state(stopped)["step"] == 1
    summary = train(config, stopped, resume=True, progress=False)
    assert summary["status"] == "finished" and summary["step"] == 6
    for (name, a), b in zip(_weights(whole).items(), _weights(stopped).values()):
        assert torch.equal(a, b), name
