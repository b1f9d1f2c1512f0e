"""FDNet's ablation switches (``loss.adversarial``, ``loss.appearance_triplet``,
``loss.reconstruction``): each removes its part from every stage, not only its weight."""

from __future__ import annotations

import copy
import csv

import pytest
import torch

from fdnet.cli import main
from fdnet.config import replace_dotted
from fdnet.errors import ConfigError
from fdnet.methods.fdnet import losses
from fdnet.methods.fdnet.config import FDNetRunConfig, preset, validate
from fdnet.methods.fdnet.model import FDNet
from fdnet.methods.fdnet.training import FDNetTraining, load_training_images, train
from fdnet.runs import load_config, load_weights
from tests.training.test_loop import make_dataset

# a projection content head on a frozen trunk, as the cpu preset's (block 4: a 4x8 map at 32x64)
PROJECTION_HEAD = {
    "model.backbone": "efficientnet-lite0",
    "model.backbone_block": 4,
    "model.input_size": [32, 64],
    "model.widths": [16],
    "model.content_head": "trunk_projection",
    "model.projection_init": "pca",
    "model.critic_input": "l2",
}


def _config(tmp_path, **overrides) -> FDNetRunConfig:
    data = tmp_path / "data"
    if not data.exists():
        make_dataset(data, size=(32, 64))
    return replace_dotted(preset("tiny"), {"data.root": str(data), **overrides})


def _initial(config: FDNetRunConfig) -> dict[str, dict[str, torch.Tensor]]:
    """The weights a fresh run of ``config`` starts from (FDNetTraining seeds before building)."""
    torch.manual_seed(config.runtime.seed)
    model = FDNet(config.model)
    return {name: {k: v.clone() for k, v in part.state_dict().items()} for name, part in model.named_parts().items()}


def _trained(config: FDNetRunConfig, run) -> dict[str, dict[str, torch.Tensor]]:
    model = FDNet(load_config(run, FDNetRunConfig).model)
    load_weights(run, model.named_parts())
    return {name: {k: v.clone() for k, v in part.state_dict().items()} for name, part in model.named_parts().items()}


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _log(run) -> tuple[list[str], list[dict]]:
    with (run / "log.csv").open(newline="") as handle:
        reader = csv.DictReader(handle)
        return list(reader.fieldnames), list(reader)


def _forbid(monkeypatch, *names):
    """Make ``losses.<name>`` fail if training ever calls it."""
    for name in names:

        def called(*args, _name=name, **kwargs):
            raise AssertionError(f"losses.{_name} was computed")

        monkeypatch.setattr(losses, name, called)


def test_the_switches_are_settings_written_to_config_yaml(tmp_path):
    config = preset("tiny")
    assert (config.loss.adversarial, config.loss.appearance_triplet, config.loss.reconstruction) == (True, True, True)
    assert config.ablated() == []
    data = make_dataset(tmp_path / "data", size=(16, 32))
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(data),
                "--preset",
                "tiny",
                "--out",
                str(run),
                "--no-progress",
                "--set",
                "loss.adversarial=false",
                "--set",
                "loss.reconstruction=false",
            ]
        )
        == 0
    )
    saved = load_config(run, FDNetRunConfig)
    assert saved.ablated() == ["adversarial", "reconstruction"]
    text = (run / "checkpoints").glob("step-*/config.yaml").__next__().read_text()
    assert "adversarial: false" in text and "appearance_triplet: true" in text and "reconstruction: false" in text


def test_without_the_critic_it_is_never_stepped_and_its_terms_never_logged(tmp_path, monkeypatch):
    config = _config(tmp_path, **{"loss.adversarial": False})
    s = config.schedule
    # the critic stage is skipped; the encoders/decoder get as many updates as in the full run
    assert config.stage_steps == (s.pretrain_autoencoder_steps, 0, s.joint_steps)
    assert config.total_steps == s.pretrain_autoencoder_steps + s.joint_steps
    assert [config.stage_at(i) for i in range(config.total_steps)] == ["autoencoder"] * s.pretrain_autoencoder_steps + [
        "joint"
    ] * s.joint_steps
    _forbid(monkeypatch, "critic_loss", "encoder_adversarial_loss", "gradient_penalty", "wasserstein_estimate")
    run = tmp_path / "run"
    summary = train(config, run, progress=False)
    assert summary["status"] == "finished" and summary["step"] == config.total_steps
    initial, trained = _initial(config), _trained(config, run)
    assert _same(trained["discriminator"], initial["discriminator"])  # bit-identical to its initialisation
    assert not _same(trained["content_encoder"], initial["content_encoder"])  # the rest did train
    columns, rows = _log(run)
    assert not {"encoder_adversarial", "critic", "wasserstein", "structure"} & set(columns)
    assert {"reconstruction", "appearance"} <= set(columns)
    assert {r["stage"] for r in rows} == {"autoencoder", "joint"}


def test_the_full_run_does_step_the_critic(tmp_path):
    """What the test above would see if the switch did nothing."""
    config = _config(tmp_path)
    run = tmp_path / "run"
    train(config, run, progress=False)
    assert not _same(_trained(config, run)["discriminator"], _initial(config)["discriminator"])
    columns, rows = _log(run)
    assert {"encoder_adversarial", "critic", "wasserstein"} <= set(columns)
    assert any(r["encoder_adversarial"] for r in rows if r["stage"] == "joint")


def test_without_the_critic_a_projection_head_stays_at_its_closed_form_start(tmp_path, monkeypatch):
    """The cpu preset's content head is moved by L_e^adv alone (the decoder reads a detached v_c):
    without the critic the descriptor is the closed-form start."""
    config = _config(tmp_path, **PROJECTION_HEAD, **{"loss.adversarial": False})
    _forbid(monkeypatch, "critic_loss", "encoder_adversarial_loss")
    run = tmp_path / "run"
    train(config, run, progress=False)
    trained = _trained(config, run)
    assert torch.count_nonzero(trained["content_encoder"]["refine"]) == 0
    assert _same(trained["discriminator"], _initial(config)["discriminator"])


def _appearance_gradient_of_reconstruction_alone(method: FDNetTraining, batch: torch.Tensor) -> list[torch.Tensor]:
    """d(w_r L_r)/d(E_a's weights) at the method's current weights, on a copy of its model."""
    model, cfg = copy.deepcopy(method.model), method.config
    model.train()
    reconstruction = model.decoder(model.content_encoder(batch), model.appearance_encoder(batch))
    rec = cfg.loss.reconstruction_weight * losses.reconstruction_loss(
        batch, reconstruction, cfg.loss.reconstruction_reduction
    )
    return list(torch.autograd.grad(rec, list(model.appearance_encoder.parameters())))


@pytest.mark.parametrize("stage", ["autoencoder", "joint"])
def test_without_the_triplet_loss_the_appearance_encoder_gets_the_reconstruction_gradient_alone(tmp_path, stage):
    """L_r reaches E_a through the decoder, so E_a still learns; what the switch removes is L_a's
    part of E_a's gradient: after one update E_a's gradient is exactly w_r dL_r/dE_a. With the
    triplet loss on it is not (so the comparison tells the two apart)."""
    # no dropout: the copy's forward pass must be the update's
    common = {"model.encoder_dropout": 0.0}
    for triplet in (False, True):
        config = _config(tmp_path, **common, **{"loss.appearance_triplet": triplet})
        method = FDNetTraining(config, load_training_images(config))
        method.model.train()
        batch = method._batch()
        expected = _appearance_gradient_of_reconstruction_alone(method, batch)
        step = 0 if stage == "autoencoder" else sum(config.stage_steps[:2])
        assert config.stage_at(step) == stage
        out = method._autoencoder_update(step, adversarial=stage == "joint", appearance=True, target=batch)
        assert ("appearance" in out) == triplet
        got = [p.grad for p in method.model.appearance_encoder.parameters()]
        same = all(torch.allclose(g, e, rtol=1e-5, atol=1e-8) for g, e in zip(got, expected))
        assert same != triplet, (
            f"triplet {'on' if triplet else 'off'}: E_a's gradient " f"{'is' if same else 'is not'} L_r's alone"
        )


def test_without_the_triplet_loss_and_reconstruction_the_appearance_encoder_never_changes(tmp_path, monkeypatch):
    config = _config(tmp_path, **{"loss.appearance_triplet": False, "loss.reconstruction": False})
    # nothing to train in the auto-encoder stage: it is skipped
    assert config.stage_steps == (0, config.schedule.pretrain_critic_steps, config.schedule.joint_steps)
    _forbid(monkeypatch, "batch_hard_triplet_loss", "reconstruction_loss")
    run = tmp_path / "run"
    train(config, run, progress=False)
    initial, trained = _initial(config), _trained(config, run)
    assert _same(trained["appearance_encoder"], initial["appearance_encoder"])
    assert _same(trained["decoder"], initial["decoder"])
    assert not _same(trained["content_encoder"], initial["content_encoder"])  # L_e^adv moved it
    columns, _ = _log(run)
    assert "appearance" not in columns and "reconstruction" not in columns and "encoder_adversarial" in columns


def test_without_reconstruction_there_is_no_decoder_loss_and_the_decoder_never_changes(tmp_path, monkeypatch):
    config = _config(tmp_path, **{"loss.reconstruction": False})
    _forbid(monkeypatch, "reconstruction_loss")
    decoded = []
    original = type(FDNet(config.model).decoder).forward
    monkeypatch.setattr(
        type(FDNet(config.model).decoder), "forward", lambda self, *a, **k: decoded.append(1) or original(self, *a, **k)
    )
    run = tmp_path / "run"
    train(config, run, progress=False)
    assert decoded == []  # not even a forward pass
    initial, trained = _initial(config), _trained(config, run)
    assert _same(trained["decoder"], initial["decoder"])
    assert not _same(trained["appearance_encoder"], initial["appearance_encoder"])  # L_a trained it
    columns, rows = _log(run)
    assert "reconstruction" not in columns and {"appearance", "encoder_adversarial"} <= set(columns)
    assert {r["stage"] for r in rows} == {"autoencoder", "critic", "joint"}


def test_impossible_combinations_are_config_errors():
    with pytest.raises(ConfigError, match="nothing would be trained"):
        validate(
            replace_dotted(
                preset("tiny"),
                {"loss.adversarial": False, "loss.appearance_triplet": False, "loss.reconstruction": False},
            )
        )
    with pytest.raises(ConfigError, match="loss.structure_weight > 0 needs loss.adversarial=true"):
        validate(replace_dotted(preset("tiny"), {"loss.adversarial": False, "loss.structure_weight": 1.0}))


def test_a_resumed_run_keeps_its_switches(tmp_path):
    config = _config(tmp_path, **{"loss.adversarial": False})
    run = tmp_path / "run"
    assert train(config, run, max_minutes=0.0, progress=False)["status"] == "time limit"
    with pytest.raises(
        ConfigError,
        match="keeps the ablation switches it started with.*loss.adversarial: saved " "false, requested true",
    ):
        train(_config(tmp_path), run, resume=True, override=True, progress=False)
    summary = train(config, run, resume=True, progress=False)
    assert summary["status"] == "finished" and summary["step"] == config.total_steps
    columns, _ = _log(run)
    assert "encoder_adversarial" not in columns


def test_with_a_projection_head_neither_l_a_nor_l_r_reaches_the_content_vector(tmp_path):
    """What docs/runs.md says of the cpu preset: its content head reads no gradient from L_a or L_r
    (the decoder reads a detached v_c), so without either the content encoder trains exactly as in
    the full run, weight for weight; without the critic it does not train at all."""
    trained = {}
    for name, switches in (
        ("full", {}),
        ("no-triplet", {"loss.appearance_triplet": False}),
        ("no-reconstruction", {"loss.reconstruction": False}),
    ):
        config = _config(tmp_path, **PROJECTION_HEAD, **switches)
        train(config, tmp_path / name, progress=False)
        trained[name] = _trained(config, tmp_path / name)
    assert torch.count_nonzero(trained["full"]["content_encoder"]["refine"]) > 0
    for name in ("no-triplet", "no-reconstruction"):
        assert _same(trained[name]["content_encoder"], trained["full"]["content_encoder"]), name
        assert _same(trained[name]["discriminator"], trained["full"]["discriminator"]), name
    assert not _same(trained["no-triplet"]["appearance_encoder"], trained["full"]["appearance_encoder"])
