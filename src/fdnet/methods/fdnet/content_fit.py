"""The closed-form start of FDNet's projection content head (``model.content_head=trunk_projection``).

Pure numpy over the trunk maps of the training images, one array per condition, each in the
traverse's frame order. Two steps, both without cross-condition place labels:

1. **Start** (``projection_init=pca``): centre on the mean of all training maps, remove the
   directions between the conditions' mean maps (what a linear appearance critic finds first;
   the residual head's ``condition_means`` start), then project on the first ``pca_dims``
   principal directions, coordinate k scaled by ``eigenvalue_k ** -pca_power``. ``pca_power``
   0.25 (half of full whitening) validated better than 0 (plain PCA) and 0.5 (full whitening) on
   Nordland and Gardens Point (docs/results.md).
2. **Mined pairs** (``projection_init=mined_pairs``, the ``cpu`` preset): FDNet's own start
   finds pairs of frames of two conditions that show the same place, then learns from them which
   directions change between conditions. A pair is kept when the frames are *mutual* best matches
   under SeqSLAM sequence similarity over ``pair_sequence_length`` consecutive frames of each
   traverse (:func:`fdnet.matching.sequence.sequence_similarity`). What this uses: the condition
   labels, and the order of the frames within each condition's folder (a traverse); no
   correspondence between conditions is given. The projection is then the learnt whitening of
   Radenović, Tolias and Chum (TPAMI 2019, "Fine-tuning CNN image retrieval with no human
   annotation", section 3.3): whiten the covariance of the pairs' differences (shrunk towards
   its mean eigenvalue by ``pair_shrinkage``, so the few hundred pairs of a small set do not
   amplify noise), then rotate to the principal directions of the whitened training maps and
   keep the first ``vector_length``.

Hand-written in numpy rather than with scikit-learn: the PCA is the whitening's
(:func:`fdnet.descriptors.whitening.principal_directions`, on the Gram matrix of a few thousand
10^4-dimensional maps), and the learnt whitening one ``eigh`` of a small (pca_dims x pca_dims)
covariance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from fdnet.descriptors.whitening import principal_directions
from fdnet.errors import DataError

log = logging.getLogger(__name__)


@dataclass
class ProjectionFit:
    """A fitted head: v_c = (x - mean) @ projection, x the flattened (normalised) trunk map."""

    mean: np.ndarray  # (D,)
    projection: np.ndarray  # (D, L)
    report: dict = field(default_factory=dict)


def _principal(x: np.ndarray, dims: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred (N, D) -> (components (D, k), eigenvalues (k,)), k <= dims, by decreasing
    eigenvalue, directions with (numerically) zero variance dropped."""
    components, values = principal_directions(x, min(int(dims), *x.shape))
    values = np.maximum(values, 0.0)
    keep = values > values[0] * 1e-9 if len(values) and values[0] > 0 else np.zeros(len(values), bool)
    return components[keep].T, values[keep]


def condition_mean_basis(maps: list[np.ndarray], mean: np.ndarray) -> np.ndarray:
    """(D, k) orthonormal basis of the directions between the conditions' mean maps."""
    means = np.stack([m.mean(0) for m in maps]) - mean
    basis, singular, _ = np.linalg.svd(means.T, full_matrices=False)
    if not singular.size or singular.max() == 0:
        return np.zeros((len(mean), 0))
    return basis[:, singular > singular.max() * 1e-6]


def mine_pairs(vectors: list[np.ndarray], sequence_length: int) -> list[tuple[int, int, int, int]]:
    """Mutual best matches between every two conditions: (condition a, frame i, condition b,
    frame j), by cosine similarity of ``vectors`` (one (N_c, L) array per condition, frame order)
    accumulated over ``sequence_length`` consecutive frames."""
    from fdnet.matching.sequence import sequence_similarity

    unit = [v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12) for v in vectors]
    pairs = []
    for a in range(len(unit)):
        for b in range(a + 1, len(unit)):
            s = (unit[a] @ unit[b].T).astype(np.float32)
            a_to_b = sequence_similarity(s, sequence_length).argmax(1)
            b_to_a = sequence_similarity(np.ascontiguousarray(s.T), sequence_length).argmax(1)
            mutual = np.flatnonzero(b_to_a[a_to_b] == np.arange(len(a_to_b)))
            pairs += [(a, int(i), b, int(a_to_b[i])) for i in mutual]
    return pairs


#: mined pairs whose next frame is mined too, at most 2 frames from the next place, per frame of the
#: shorter traverse: 0.63-0.79 between Nordland's seasons, 0.22-0.66 between Gardens Point's
#: conditions, 0.05-0.11 for traverses of different places (docs/results.md)
MIN_ROUTE_CONSISTENCY = 0.15


def route_consistency(pairs: list[tuple[int, int, int, int]], lengths: list[int], slack: int = 2) -> dict:
    """For every two conditions a, b: the fraction of frames of the shorter traverse whose mined
    pair (i, j) is followed by a mined pair (i + 1, j') with |j' - (j + 1)| <= ``slack``. Two
    traverses of one route advance together; mutual matches between unrelated places do not."""
    mined = {(a, i, b): j for a, i, b, j in pairs}
    counts: dict[tuple[int, int], int] = {}
    for (a, i, b), j in mined.items():
        follower = mined.get((a, i + 1, b))
        if follower is not None and abs(follower - (j + 1)) <= slack:
            counts[(a, b)] = counts.get((a, b), 0) + 1
    return {
        (a, b): counts.get((a, b), 0) / max(min(lengths[a], lengths[b]), 1)
        for a in range(len(lengths))
        for b in range(a + 1, len(lengths))
    }


def learnt_whitening(
    projected: list[np.ndarray], pairs: list[tuple[int, int, int, int]], shrinkage: float
) -> np.ndarray:
    """(k, k) transform: whiten the pairs' difference covariance (shrunk), then rotate to the
    principal directions of the whitened training vectors, by decreasing variance."""
    diff = np.stack([projected[a][i] - projected[b][j] for a, i, b, j in pairs])
    pair_cov = diff.T @ diff / len(diff)
    k = pair_cov.shape[0]
    pair_cov += shrinkage * np.trace(pair_cov) / k * np.eye(k)
    values, vecs = np.linalg.eigh(pair_cov)
    whiten = (vecs / np.sqrt(values)) @ vecs.T  # pair_cov ** -1/2
    rot_values, rot = np.linalg.eigh(np.cov((np.concatenate(projected) @ whiten).T))
    return whiten @ rot[:, np.argsort(rot_values)[::-1]]


def fit_projection(
    maps: list[np.ndarray],
    length: int,
    init: str = "mined_pairs",
    pca_dims: int = 1024,
    pca_power: float = 0.25,
    pair_sequence_length: int = 5,
    pair_shrinkage: float = 1.0,
    names: list[str] | None = None,
) -> ProjectionFit:
    """The head's start from the training maps (one (N_c, D) float array per condition, frame
    order; ``names`` the conditions', for messages). ``init``: ``pca`` (step 1 of the module
    docstring) or ``mined_pairs`` (steps 1 and 2). With fewer training images than ``length``
    the vector keeps its length and the last columns are zero (the maps span at most one fewer
    directions than there are images)."""
    maps = [np.asarray(m, dtype=np.float64).reshape(len(m), -1) for m in maps]
    total = sum(len(m) for m in maps)
    if total < 3:
        raise DataError(f"fdnet: the projection head needs at least 3 training images, got {total}")
    mean = np.concatenate(maps).mean(0)
    basis = condition_mean_basis(maps, mean)

    def remove(x: np.ndarray) -> np.ndarray:
        x = x - mean
        return x - (x @ basis) @ basis.T

    removed = [remove(m) for m in maps]
    components, eigenvalues = _principal(np.concatenate(removed), pca_dims)
    start = components / eigenvalues**pca_power  # (D, k)
    report = {
        "condition_directions_removed": int(basis.shape[1]),
        "pca_dims": int(start.shape[1]),
        "training_images": int(total),
    }
    if init == "mined_pairs":
        projected = [r @ start for r in removed]
        pairs = mine_pairs(projected, pair_sequence_length)
        report["mined_pairs"] = len(pairs)
        if len(pairs) < 2:
            raise DataError(
                f"fdnet: only {len(pairs)} mutual matches were found between the training conditions; "
                "the mined-pair start needs conditions that are traverses of the same route "
                "(use model.projection_init=pca otherwise)"
            )
        consistency = route_consistency(pairs, [len(m) for m in maps])
        report["route_consistency"] = round(float(np.mean(list(consistency.values()))), 3)
        if report["route_consistency"] < MIN_ROUTE_CONSISTENCY:
            raise DataError(
                f"fdnet: the training conditions do not look like traverses of one route: only "
                f"{report['route_consistency']:.0%} of the frames' mutual matches advance together with "
                f"the next frame's (traverses of one route: 22-79 %, of different places: 5-11 %); the "
                "mined-pair start needs conditions that revisit the same places in the same order "
                "(use model.projection_init=pca otherwise)"
            )
        names = list(names) if names is not None and len(names) == len(maps) else [str(i) for i in range(len(maps))]
        for (a, b), value in consistency.items():
            if value < MIN_ROUTE_CONSISTENCY:
                log.warning(
                    "conditions %s and %s share few route-consistent matches (%.0f%%): are they "
                    "traverses of the same route?",
                    names[a],
                    names[b],
                    100 * value,
                )
        head = start @ learnt_whitening(projected, pairs, pair_shrinkage)
    elif init == "pca":
        head = start
    else:
        raise DataError(f"fdnet: unknown projection_init {init!r}")
    head = head[:, :length]
    if head.shape[1] < length:
        head = np.concatenate([head, np.zeros((head.shape[0], length - head.shape[1]))], axis=1)
    # The removal of the condition directions is linear, so it folds into the projection.
    projection = head - basis @ (basis.T @ head)
    report["rank"] = int(min(length, start.shape[1]))
    log.debug("projection head start: %s", report)  # FDNetTraining.start logs it at INFO
    return ProjectionFit(mean.astype(np.float32), projection.astype(np.float32), report)
