"""The projection head's closed-form start (fdnet.methods.fdnet.content_fit) on made maps."""

import numpy as np
import pytest

from fdnet.errors import DataError
from fdnet.methods.fdnet.content_fit import fit_projection, mine_pairs


def made_route(frames=160, dim=240, noise_dims=24, seed=0):
    """Two traverses of one route: each frame's place signal (a smooth walk in a 60-d subspace)
    plus, per condition, a constant offset and strong per-frame appearance noise in a subspace of
    its own (larger in the second condition, like night)."""
    rng = np.random.default_rng(seed)
    basis, _ = np.linalg.qr(rng.normal(size=(dim, 60 + noise_dims)))
    place_basis, noise_basis = basis[:, :60], basis[:, 60:]
    walk = np.cumsum(rng.normal(size=(frames, 60)), axis=0)
    walk += rng.normal(scale=4.0, size=walk.shape)  # neighbouring frames differ
    places = walk @ place_basis.T
    conditions = []
    for scale, offset in ((3.0, 0.0), (9.0, 5.0)):
        noise = rng.normal(scale=scale, size=(frames, noise_dims)) @ noise_basis.T
        conditions.append(places + offset * rng.normal(size=dim) + noise + rng.normal(scale=0.3, size=places.shape))
    return conditions


def recall_at_1(fit, query, reference):
    q = (query - fit.mean) @ fit.projection
    r = (reference - fit.mean) @ fit.projection
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return float(np.mean((q @ r.T).argmax(1) == np.arange(len(q))))


def test_condition_mean_direction_is_removed():
    a, b = made_route()
    fit = fit_projection([a, b], 32, init="pca", pca_dims=64)
    va = (a.mean(0) - fit.mean) @ fit.projection
    vb = (b.mean(0) - fit.mean) @ fit.projection
    typical = np.abs((a - fit.mean) @ fit.projection).max()
    np.testing.assert_allclose(va, vb, atol=1e-6 * typical)
    assert fit.projection.shape == (a.shape[1], 32)
    assert fit.report["condition_directions_removed"] == 1


def test_mined_pairs_are_the_route_correspondences_and_improve_matching():
    a, b = made_route()
    pairs = mine_pairs([a - a.mean(0), b - b.mean(0)], sequence_length=5)
    assert len(pairs) > 100
    assert np.mean([i == j for _, i, _, j in pairs]) > 0.95
    # held-out frames: fitted on the first 120 frames of each traverse, tested on the last 40
    train = [a[:120], b[:120]]
    pca = fit_projection(train, 32, init="pca", pca_dims=80)
    mined = fit_projection(train, 32, init="mined_pairs", pca_dims=80)
    start, learnt = recall_at_1(pca, b[120:], a[120:]), recall_at_1(mined, b[120:], a[120:])
    assert learnt >= start + 0.2, (start, learnt)


def test_traverses_of_different_places_are_refused():
    a, _ = made_route(seed=0)
    _, b = made_route(seed=5)  # another route: its places are not a's
    with pytest.raises(DataError, match="do not look like traverses of one route"):
        fit_projection([a, b], 32, init="mined_pairs", pca_dims=80)
    same = fit_projection(list(made_route(seed=0)), 32, init="mined_pairs", pca_dims=80)
    assert same.report["route_consistency"] > 0.5


def test_fewer_images_than_the_length_keeps_the_length():
    a, b = made_route(frames=20)
    fit = fit_projection([a, b], 64, init="pca")
    assert fit.projection.shape[1] == 64
    assert fit.report["rank"] == 38  # 40 images: centring and the condition direction take one each
    assert np.all(fit.projection[:, 38:] == 0)


def test_conditions_without_common_places_are_refused():
    rng = np.random.default_rng(1)
    # two frames each: a mutual pair needs a sequence, and unrelated noise rarely gives two
    with pytest.raises(DataError, match="mutual matches"):
        fit_projection([rng.normal(size=(1, 50)), rng.normal(size=(2, 50))], 4, init="mined_pairs")


def test_a_condition_pair_of_another_route_is_named_in_the_warning(caplog):
    a, b = made_route(seed=0)
    _, other = made_route(seed=5)  # a third condition of other places: its two pairs are low
    fit_projection([a, b, other], 32, init="mined_pairs", pca_dims=80, names=["summer", "winter", "elsewhere"])
    warned = [r.getMessage() for r in caplog.records if "few route-consistent" in r.getMessage()]
    assert len(warned) == 2 and all("elsewhere" in m for m in warned), warned
