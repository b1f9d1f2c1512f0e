"""The experiment runner on a tiny synthetic route, with test descriptors defined here."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.data.dataset import RouteDataset
from fdnet.data.split import aligned_split
from fdnet.descriptors.base import Descriptor, l2_normalize
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.evaluation.experiment import ScoringSettings, evaluate_matrix, evaluate_method
from fdnet.matching.similarity import similarity_matrix
from fdnet.metrics import RECALL_OVER_QUERIES, VPRBENCH, evaluate_similarity, top_k_of_matrix

from conftest import write_day_dusk_route


class TinyPixels(Descriptor):
    """Mean-centred 8x8 grey pixels, cosine: invariant to the brightness change of 'dusk'."""

    name = "tiny-pixels"

    def __init__(self):
        self.input_size = (8, 8)

    @property
    def dim(self) -> int:
        return 64

    def describe(self, images):
        grey = images.mean(axis=3).reshape(len(images), -1)
        return l2_normalize(grey - grey.mean(axis=1, keepdims=True))


class FittedL1(TinyPixels):
    """Needs fit (records what it saw); compares by negative L1 distance, not a dot product."""

    name = "fitted-l1"
    dot_product_similarity = False

    def __init__(self):
        super().__init__()
        self.fitted_on = None

    @property
    def needs_fit(self) -> bool:
        return self.fitted_on is None

    def fit(self, images_or_paths):
        self.fitted_on = list(images_or_paths)

    def similarity(self, queries, references):
        return -np.abs(queries[:, None, :] - references[None, :, :]).sum(axis=2)


def make_route(root, frames: int = 12, seed: int = 0):
    """Two conditions of one route: 'day' random patterns; 'dusk' = darker, noisy copies."""
    return write_day_dusk_route(root, np.random.default_rng(seed), frames)


@pytest.fixture
def split(tmp_path):
    return aligned_split(RouteDataset.from_folder(make_route(tmp_path)), "day", "dusk", tolerance=0)


def test_evaluate_method_end_to_end(split):
    result = evaluate_method(
        TinyPixels(), split, ScoringSettings(protocols=(RECALL_OVER_QUERIES, VPRBENCH)), keep_similarity=True
    )
    roq = result.metrics[RECALL_OVER_QUERIES]
    assert roq.recall_at_n[1] == 1.0 and roq.recall_at_100_precision == 1.0
    assert result.metrics[VPRBENCH].top1_accuracy == 1.0
    np.testing.assert_array_equal(result.retrieved[:, 0], np.arange(12))
    assert result.similarity.shape == (12, 12)
    assert result.timing["ms_per_image"] >= 0 and result.timing["ms_per_query"] >= 0
    assert result.settings["dim"] == 64
    d = result.to_dict(VPRBENCH)
    assert d["protocol"] == "vprbench" and d["method"] == "tiny-pixels" and d["num_queries"] == 12


def test_runner_fits_and_uses_the_descriptors_own_similarity(split):
    descriptor = FittedL1()
    messages = []
    result = evaluate_method(descriptor, split, keep_similarity=True, log=messages.append)
    assert descriptor.fitted_on == list(split.reference.paths)
    assert any("fitting" in m for m in messages)
    assert any("fitted on the 12 reference images" in n for n in result.notes)
    # ranking must come from the L1 similarity, not from a dot product of the vectors
    from fdnet.descriptors.base import describe_paths

    q = describe_paths(descriptor, split.query.paths)
    r = describe_paths(descriptor, split.reference.paths)
    expected, _ = top_k_of_matrix(descriptor.similarity(q, r), result.retrieved.shape[1])
    np.testing.assert_array_equal(result.retrieved, expected)
    np.testing.assert_allclose(result.similarity, descriptor.similarity(q, r), rtol=1e-5)


def test_sequence_matching_option(split):
    result = evaluate_method(TinyPixels(), split, sequence_length=3)
    assert result.settings["sequence_length"] == 3
    assert result.metrics[RECALL_OVER_QUERIES].recall_at_n[1] == 1.0


def test_evaluate_matrix_equals_metrics_on_the_same_matrix(rng):
    from fdnet.data.groundtruth import GroundTruth

    s = rng.random((30, 25))
    gt = GroundTruth.from_frames(np.arange(30), np.arange(25), 1)
    result = evaluate_matrix(s, gt, "random")
    direct = evaluate_similarity(s, gt)
    assert result.metrics[RECALL_OVER_QUERIES].auc_pr == direct.auc_pr
    assert result.to_dict()["recall_at_n"] == {str(k): v for k, v in direct.recall_at_n.items()}


def test_descriptor_path_agrees_with_the_matrix_path(split):
    d = TinyPixels()
    from fdnet.descriptors.base import describe_paths

    s = similarity_matrix(describe_paths(d, split.query.paths), describe_paths(d, split.reference.paths))
    by_runner = evaluate_method(d, split, ScoringSettings(protocols=(VPRBENCH,))).metrics[VPRBENCH]
    by_matrix = evaluate_similarity(s, split.ground_truth, VPRBENCH)
    assert by_runner.auc_pr == pytest.approx(by_matrix.auc_pr)
    assert by_runner.recall_at_n == by_matrix.recall_at_n


def test_large_splits_are_ranked_without_the_full_matrix(split):
    """Beyond max_matrix_entries no (Q, R) matrix is kept or made: sequence matching runs in
    blocks of queries and gives the same ranking as the full matrix; plots are skipped with a note."""
    full = evaluate_method(FittedL1(), split, sequence_length=3)
    blocked = evaluate_method(FittedL1(), split, sequence_length=3, max_matrix_entries=30, keep_similarity=True)
    np.testing.assert_array_equal(blocked.retrieved, full.retrieved)
    np.testing.assert_allclose(blocked.scores, full.scores, rtol=1e-6)
    assert blocked.similarity is None and any("too large" in n for n in blocked.notes)
    plain = evaluate_method(TinyPixels(), split, pipeline=PipelineSettings(workers=0))
    assert plain.similarity is None  # never made unless asked for


@pytest.mark.parametrize(
    "setting, message",
    [
        ("radius_m=5", "radius_m: evaluation on image folders has no positions"),
        ("radius_s=2", "radius_s: evaluation on image folders has no timestamps"),
    ],
)
def test_a_neighbourhood_the_split_cannot_give_is_refused_before_describing(split, setting, message):
    from fdnet.decisions.acceptance import parse_acceptance
    from fdnet.errors import ConfigError

    class Untouchable(TinyPixels):
        def describe(self, images):
            raise AssertionError("described before the rule was checked")

    with pytest.raises(ConfigError, match=message):
        evaluate_method(
            Untouchable(),
            split,
            ScoringSettings(acceptance=[parse_acceptance("margin", [setting])]),
            PipelineSettings(workers=0),
        )


def test_a_rule_that_looks_at_images_is_refused_on_a_bare_matrix(rng):
    from fdnet.data.groundtruth import GroundTruth
    from fdnet.errors import ConfigError

    with pytest.raises(ConfigError, match="looks at the images, but a similarity matrix has no image paths"):
        evaluate_matrix(rng.random((4, 4)), GroundTruth.aligned(4, 4, 0), "m", ScoringSettings(acceptance=["verified"]))
