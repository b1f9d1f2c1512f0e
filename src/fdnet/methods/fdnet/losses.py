"""FDNet's losses (paper section 3.2, eq. 3-10; Algorithm 2), as small composable functions.

* :func:`reconstruction_loss` - L_r, mean squared error between what the encoders saw and the
  decoder's output (the paper writes a sum; the mean only rescales it and keeps the loss
  independent of image size, so one weight works for every input size).
* :func:`batch_hard_triplet_loss` - L_a on appearance vectors, batch-hard mining
  (Hermans et al. 2017, "In Defense of the Triplet Loss"): for each anchor the FARTHEST positive
  (same domain) and the NEAREST negative (other domain), squared L2 distances, margin alpha.
  The paper's Algorithm 2 says "maximum distance" for the negative as well; that is a typo: its
  own text (section 4.3) and the triplet literature take the minimum.
* :func:`sample_pairs` - the labelled pairs of content vectors the discriminator judges.
* :func:`critic_loss` - L_d^adv, the WGAN-GP objective (Gulrajani et al. 2017; paper eq. 9).
* :func:`encoder_adversarial_loss` - L_e^adv = -L_d^adv without the penalty (paper eq. 8).

Pairs and the WGAN sign convention (the paper leaves both implicit):
D_a scores a pair of content vectors; "same domain" pairs play the role of the real samples and
"different domain" pairs the generated ones. The critic minimises
``E[D(different)] - E[D(same)] + lambda_gp * E[(||grad D(v_hat)||_2 - 1)^2]``, so it learns to
score same-domain pairs high. ``v_hat = eps * same + (1 - eps) * different`` interpolates, with
one eps ~ U(0, 1) per pair, between the i-th same-domain pair and the i-th different-domain pair
(both concatenated vectors of length 2L): the paper's "straight lines connecting pairs of
training data with different labels". The encoder minimises ``E[D(same)] - E[D(different)]``:
it is rewarded when the critic cannot tell same-domain pairs from different-domain pairs, i.e.
when the content vectors carry no appearance information.
"""

from __future__ import annotations

import torch


def reconstruction_loss(target: torch.Tensor, reconstruction: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """L_r. ``"sum"``: paper eq. 3, ||x - x~||^2 summed over every value of an image, averaged
    over the batch (so the batch size does not rescale the loss); ``"mean"``: mean squared error
    per value."""
    squared = (reconstruction.float() - target.float()) ** 2
    if reduction == "sum":
        return squared.flatten(1).sum(1).mean()
    if reduction == "mean":
        return squared.mean()
    raise ValueError(f"reconstruction reduction {reduction!r}: choose mean or sum")


def squared_distances(vectors: torch.Tensor) -> torch.Tensor:
    """(N, L) -> (N, N) squared Euclidean distances (exact, non-negative)."""
    diff = vectors.unsqueeze(1) - vectors.unsqueeze(0)
    return (diff * diff).sum(-1)


def structure_loss(vectors: torch.Tensor, reference: torch.Tensor, domains: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between the cosine similarities of ``vectors`` and of
    ``reference`` (same rows), over the pairs i != j of one domain: how much the within-domain
    similarity structure changed. 0 when no domain has two rows."""
    a = torch.nn.functional.normalize(vectors.flatten(1).float(), dim=1)
    b = torch.nn.functional.normalize(reference.flatten(1).float(), dim=1)
    same = domains.view(-1, 1) == domains.view(1, -1)
    same.fill_diagonal_(False)
    if not bool(same.any()):
        return vectors.sum() * 0.0
    return ((a @ a.T - b @ b.T)[same] ** 2).mean()


def batch_hard_triplet_loss(vectors: torch.Tensor, domains: torch.Tensor, margin: float = 0.1) -> torch.Tensor:
    """L_a (paper eq. 5 with Algorithm 2's hard triplets), averaged over the B*N_d anchors.

    ``vectors`` (N, L) appearance vectors; ``domains`` (N,) integer domain (= condition) labels.
    Every anchor needs at least one other image of its domain and one of another domain.
    """
    vectors = vectors.float()
    dist = squared_distances(vectors)
    same = domains.unsqueeze(0) == domains.unsqueeze(1)
    eye = torch.eye(len(domains), dtype=torch.bool, device=vectors.device)
    positives = same & ~eye
    negatives = ~same
    if not bool(positives.any(1).all()) or not bool(negatives.any(1).all()):
        raise ValueError("batch-hard triplets need >= 2 images per domain and >= 2 domains")
    hardest_positive = dist.masked_fill(~positives, float("-inf")).amax(1)
    hardest_negative = dist.masked_fill(~negatives, float("inf")).amin(1)
    return torch.relu(hardest_positive - hardest_negative + margin).mean()


def sample_pairs(domains: torch.Tensor, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of labelled pairs for the discriminator, one of each kind per anchor.

    For every image i of the batch: a same-domain partner (another image of its domain, chosen
    at random) and a different-domain partner (a random image of a random other domain).
    Returns ``(same, different)``, each (N, 2) index pairs (anchor, partner). Random order of the
    anchors is kept, so both orders (x_i, x_j) and (x_j, x_i) occur and D_a learns a symmetric
    judgement.
    """
    n = len(domains)
    device = domains.device
    # For each anchor, a random score per candidate; mask the invalid ones and take the argmax:
    # a uniform choice among the valid partners, vectorised.
    scores = torch.rand((n, n), generator=generator).to(device)
    same_mask = domains.unsqueeze(0) == domains.unsqueeze(1)
    same_mask &= ~torch.eye(n, dtype=torch.bool, device=device)
    diff_mask = domains.unsqueeze(0) != domains.unsqueeze(1)
    anchors = torch.arange(n, device=device)
    same_partner = scores.masked_fill(~same_mask, -1.0).argmax(1)
    diff_partner = scores.masked_fill(~diff_mask, -1.0).argmax(1)
    return torch.stack([anchors, same_partner], 1), torch.stack([anchors, diff_partner], 1)


def pair_vectors(vectors: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """(N, L) vectors, (P, 2) index pairs -> (P, 2L) concatenations."""
    return torch.cat([vectors[pairs[:, 0]], vectors[pairs[:, 1]]], dim=1)


def gradient_penalty(
    critic, same: torch.Tensor, different: torch.Tensor, generator: torch.Generator | None = None
) -> torch.Tensor:
    """E[(||grad_v D(v_hat)||_2 - 1)^2] on v_hat between same- and different-domain pairs."""
    eps = torch.rand((same.shape[0], 1), generator=generator).to(same.device)
    v_hat = (eps * same.detach() + (1 - eps) * different.detach()).requires_grad_(True)
    scores = critic(v_hat)
    (grad,) = torch.autograd.grad(scores.sum(), v_hat, create_graph=True)
    return ((grad.norm(2, dim=1) - 1.0) ** 2).mean()


def wasserstein_estimate(critic, same: torch.Tensor, different: torch.Tensor) -> torch.Tensor:
    """E[D(same)] - E[D(different)]: how well the critic tells the two kinds of pairs apart."""
    return critic(same).mean() - critic(different).mean()


def critic_loss(
    critic,
    same: torch.Tensor,
    different: torch.Tensor,
    gp_weight: float = 10.0,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """L_d^adv (paper eq. 9, WGAN-GP form). ``critic`` maps (P, 2L) pairs to (P,) scores.

    Returns ``(loss, wasserstein_estimate)``; the estimate (detached) is what the log shows.
    """
    distance = wasserstein_estimate(critic, same, different)
    penalty = gradient_penalty(critic, same, different, generator)
    return -distance + gp_weight * penalty, distance.detach()


def encoder_adversarial_loss(critic, same: torch.Tensor, different: torch.Tensor) -> torch.Tensor:
    """L_e^adv = -L_d^adv (paper eq. 8), without the penalty term (it does not depend on E_c)."""
    return wasserstein_estimate(critic, same, different)
