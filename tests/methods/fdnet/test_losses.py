"""Each loss on hand-made tensors whose right value is known."""

import pytest
import torch

from fdnet.methods.fdnet import losses


def test_reconstruction_is_mse():
    target = torch.zeros(1, 1, 2, 2)
    out = torch.tensor([[[[1.0, 0.0], [0.0, 3.0]]]])
    assert losses.reconstruction_loss(target, out).item() == pytest.approx((1 + 9) / 4)


def test_batch_hard_triplet_takes_farthest_positive_and_nearest_negative():
    # 1-D appearance vectors; domains 0: {0, 1}, 1: {3, 5}. Squared distances:
    # anchor 0: hardest positive 1, nearest negative 9 -> max(1 - 9 + 0.1, 0) = 0
    # anchor 1: 1 vs 4 -> 0;  anchor 3: 4 vs 4 -> 0.1 (a farthest negative, 9, would give 0)
    # anchor 5: 4 vs 16 -> 0. Mean over the 4 anchors = 0.025.
    v = torch.tensor([[0.0], [1.0], [3.0], [5.0]])
    d = torch.tensor([0, 0, 1, 1])
    assert losses.batch_hard_triplet_loss(v, d, margin=0.1).item() == pytest.approx(0.025)
    assert losses.batch_hard_triplet_loss(v, d, margin=0.0).item() == pytest.approx(0.0)


def test_batch_hard_triplet_gradient_pulls_and_pushes():
    v = torch.tensor([[0.0], [1.0], [3.0], [5.0]], requires_grad=True)
    losses.batch_hard_triplet_loss(v, torch.tensor([0, 0, 1, 1]), margin=0.1).backward()
    # only anchor 3 is active: gradient descent moves its positive (5) down toward 3 and its
    # nearest negative (1) down, away from 3; the farther negative (0) gets no gradient
    assert v.grad[3, 0] > 0 and v.grad[1, 0] > 0 and v.grad[0, 0] == 0
    assert v.grad[1, 0] == pytest.approx(2 * (3 - 1) / 4)


def test_batch_hard_triplet_needs_positives():
    with pytest.raises(ValueError):
        losses.batch_hard_triplet_loss(torch.zeros(2, 3), torch.tensor([0, 1]))


def test_sample_pairs_labels():
    g = torch.Generator().manual_seed(0)
    domains = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2, 2])
    same, different = losses.sample_pairs(domains, g)
    assert same.shape == different.shape == (9, 2)
    assert torch.equal(same[:, 0], torch.arange(9))
    assert (domains[same[:, 0]] == domains[same[:, 1]]).all() and (same[:, 0] != same[:, 1]).all()
    assert (domains[different[:, 0]] != domains[different[:, 1]]).all()


class _Linear(torch.nn.Module):
    """D(v) = w . v: its gradient w.r.t. v is w everywhere, so the penalty is (|w| - 1)^2."""

    def __init__(self, w):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(w))

    def forward(self, v):
        return v @ self.w


def test_wgan_gp_critic_and_encoder_losses():
    same = torch.tensor([[1.0, 0.0], [3.0, 0.0]])  # D = 2 * x: scores 2, 6 (mean 4)
    different = torch.tensor([[0.0, 0.0], [1.0, 5.0]])  # scores 0, 2 (mean 1)
    critic = _Linear([2.0, 0.0])  # |w| = 2 -> penalty (2 - 1)^2 = 1
    loss, distance = losses.critic_loss(critic, same, different, gp_weight=10.0)
    assert distance.item() == pytest.approx(3.0)
    assert loss.item() == pytest.approx(-3.0 + 10.0 * 1.0)
    unit = _Linear([0.6, 0.8])  # |w| = 1 -> no penalty
    loss, distance = losses.critic_loss(unit, same, different, gp_weight=10.0)
    expected = (0.6 + 1.8) / 2 - (0.0 + 0.6 + 4.0) / 2
    assert loss.item() == pytest.approx(-expected, abs=1e-6)
    # the encoder's term is the negated critic objective without the penalty
    assert losses.encoder_adversarial_loss(unit, same, different).item() == pytest.approx(expected, abs=1e-6)


def test_gradient_penalty_uses_interpolates_between_labels():
    # D(v) = |v|^2 / 2 has gradient v: the penalty depends on where v_hat lies.
    critic = lambda v: 0.5 * (v * v).sum(1)  # noqa: E731
    same = torch.tensor([[1.0, 0.0]])
    different = torch.tensor([[1.0, 0.0]])
    # identical endpoints: v_hat = (1, 0), |grad| = 1 -> zero penalty whatever eps is drawn
    assert losses.gradient_penalty(critic, same, different).item() == pytest.approx(0.0, abs=1e-6)
    far = torch.tensor([[3.0, 0.0]])
    assert losses.gradient_penalty(critic, far, far).item() == pytest.approx(4.0)


def test_reconstruction_sum_is_eq3_per_image_and_mean_is_per_value():
    import torch

    from fdnet.methods.fdnet.losses import reconstruction_loss

    target = torch.zeros(2, 3, 4, 5)
    recon = torch.ones(2, 3, 4, 5)
    recon[1] *= 2.0
    assert float(reconstruction_loss(target, recon, "sum")) == pytest.approx((60 * 1 + 60 * 4) / 2)
    assert float(reconstruction_loss(target, recon, "mean")) == pytest.approx((1 + 4) / 2)
    with pytest.raises(ValueError):
        reconstruction_loss(target, recon, "max")


def test_structure_loss_sees_within_domain_changes_only():
    g = torch.Generator().manual_seed(0)
    reference = torch.randn(6, 10, generator=g)
    domains = torch.tensor([0, 0, 0, 1, 1, 1])
    assert losses.structure_loss(reference * 3.0, reference, domains) < 1e-10, "scale does not matter"
    # moving one domain as a whole (a shift of every vector of domain 1 by the same offset) changes
    # cross-domain similarities a lot but within-domain ones less than an unrelated change does
    shuffled = reference[torch.tensor([1, 2, 0, 4, 5, 3])]
    assert losses.structure_loss(shuffled, reference, domains) > 0.01
    only_cross = reference.clone()
    only_cross[3:] = -only_cross[3:]  # flips cross-domain cosines, keeps within-domain ones
    assert losses.structure_loss(only_cross, reference, domains) < 1e-10
    assert losses.structure_loss(reference, reference, torch.arange(6)) == 0.0  # no pair within a domain


# the learnt encoder (batch-centred reference) and the residual head on a frozen trunk (the head's centring)
RESIDUAL_HEAD = {
    "model.backbone": "efficientnet-lite0",
    "model.backbone_block": 4,
    "model.input_size": [32, 64],
    "model.widths": [16],
    "model.content_head": "trunk_residual",
}


@pytest.mark.parametrize("model", [{}, RESIDUAL_HEAD], ids=["learnt-encoder", "residual-head"])
def test_fdnet_joint_step_adds_the_structure_loss_only_when_weighted(tmp_path, model):
    from fdnet.config import replace_dotted
    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.training import FDNetTraining, load_training_images
    from tests.training.test_loop import make_dataset

    config = replace_dotted(preset("tiny"), {"data.root": str(make_dataset(tmp_path / "data")), **model})
    joint = config.schedule.pretrain_autoencoder_steps + config.schedule.pretrain_critic_steps
    assert "structure" not in FDNetTraining(config, load_training_images(config)).train_step(joint)
    weighted = replace_dotted(config, {"loss.structure_weight": 2.0})
    out = FDNetTraining(weighted, load_training_images(weighted)).train_step(joint)
    assert out["structure"] >= 0.0 and out["structure"] == out["structure"]
