"""Acceptance rules on constructed candidates whose answers are worked out by hand."""

import numpy as np
import pytest

from fdnet.decisions import acceptance
from fdnet.decisions.acceptance import (
    Candidates,
    Rule,
    decide,
    parse_acceptance,
    parse_acceptance_list,
    register_rule,
)
from fdnet.errors import ConfigError, DataError
from fdnet.matching.sequence import sequence_similarity, sequence_top_k
from fdnet.matching.similarity import top_k_of_matrix

# query 0: best reference 5; 6 and 4 are its neighbours (radius 1); 20 is the best outside (0.5)
# query 1: best reference 1; 0 and 2 are neighbours; 9 is the best outside (0.69)
RETRIEVED = np.array([[5, 6, 4, 20, 3], [1, 9, 2, 3, 0]])
SCORES = np.array([[0.9, 0.85, 0.8, 0.5, 0.4], [0.7, 0.69, 0.6, 0.5, 0.4]])


def scores_of(rule, settings=(), **candidates):
    c = Candidates(candidates.pop("retrieved", RETRIEVED), candidates.pop("scores", SCORES), **candidates)
    return decide(parse_acceptance(rule, list(settings)), c)


def test_raw_is_the_best_similarity():
    d = scores_of("raw")
    np.testing.assert_allclose(d.score, [0.9, 0.7])
    np.testing.assert_array_equal(d.match, [5, 1])


def test_margin_skips_the_neighbourhood_of_the_best():
    np.testing.assert_allclose(scores_of("margin", ["radius=1"]).score, [0.9 - 0.5, 0.7 - 0.69])
    # radius 0: only the best itself is excluded, the runner-up counts
    np.testing.assert_allclose(scores_of("margin", ["radius=0"]).score, [0.9 - 0.85, 0.7 - 0.69])
    # radius 2: query 0's reference 3 is a neighbour too (still 0.5 from 20); query 1's 3 too -> 9 stays
    np.testing.assert_allclose(scores_of("margin", ["radius=2"]).score, [0.4, 0.01])


def test_ratio_is_one_minus_lowe_ratio_of_distances_below_the_ceiling():
    # d = 1 - s: query 0 d_best 0.1, d_out 0.5 -> 1 - 0.2; query 1 0.3 / 0.31
    np.testing.assert_allclose(scores_of("ratio", ["radius=1"]).score, [0.8, 1 - 0.3 / 0.31])


def test_ratio_with_a_similarity_whose_ceiling_is_zero():
    # SAD-like: similarity = -distance, ceiling 0; distances 1 (best) and 4 (outside) -> 1 - 1/4
    d = scores_of(
        "ratio",
        ["radius=1"],
        retrieved=np.array([[3, 4, 9]]),
        scores=np.array([[-1.0, -2.0, -4.0]]),
        similarity_ceiling=0.0,
    )
    np.testing.assert_allclose(d.score, [0.75])


def test_ratio_refuses_a_similarity_above_its_ceiling():
    with pytest.raises(DataError, match="above the declared ceiling"):
        scores_of("ratio", retrieved=np.array([[3, 9]]), scores=np.array([[2.0, 1.0]]))
    # the ceiling can be declared for the data
    np.testing.assert_allclose(
        scores_of("ratio", ["ceiling=3"], retrieved=np.array([[3, 9]]), scores=np.array([[2.0, 1.0]])).score, [0.5]
    )


def test_margin_by_time_and_by_position():
    times = np.arange(30, dtype=float) * 0.5  # reference i at i/2 seconds
    # radius_s 0.5 = one frame either side -> like radius 1
    np.testing.assert_allclose(scores_of("margin", ["radius_s=0.5"], reference_times=times).score, [0.4, 0.01])
    positions = np.zeros((30, 2))
    positions[20] = positions[5]  # reference 20 is a revisit of 5's place: same position
    positions[:, 0] += np.where(np.arange(30) == 20, 5.0, np.arange(30))  # 20 sits at x=5 like reference 5
    # within 1.5 m of reference 5 (x=5): 4, 6 and 20 -> best outside for query 0 is 3 (0.4)
    np.testing.assert_allclose(scores_of("margin", ["radius_m=1.5"], reference_positions=positions).score, [0.5, 0.01])


def test_neighbourhood_in_time_or_space_needs_the_arrays():
    with pytest.raises(ConfigError, match="timestamps"):
        scores_of("margin", ["radius_s=2"])
    with pytest.raises(ConfigError, match="positions"):
        scores_of("margin", ["radius_m=2"])


def test_no_outside_candidate_falls_back_to_the_last_score():
    # every candidate within radius 3 of the best: the k-th score (0.6) bounds the outside from above
    d = scores_of("margin", ["radius=3"], retrieved=np.array([[5, 6, 4]]), scores=np.array([[0.9, 0.8, 0.6]]))
    np.testing.assert_allclose(d.score, [0.3])
    # faiss pads missing candidates with -1: they are ignored
    d = scores_of("margin", ["radius=1"], retrieved=np.array([[5, 9, -1]]), scores=np.array([[0.9, 0.7, -3e38]]))
    np.testing.assert_allclose(d.score, [0.2])


@pytest.mark.parametrize("radius", [0, 1, 3])
def test_depth_2r_plus_2_gives_the_exact_margin(radius):
    rng = np.random.default_rng(radius)
    sim = rng.normal(size=(40, 60))
    spec = parse_acceptance("margin", [f"radius={radius}"])
    assert spec.depth == 2 * radius + 2
    idx, scores = top_k_of_matrix(sim, spec.depth)
    got = decide(spec, Candidates(idx, scores)).score
    best = sim.argmax(axis=1)
    far = np.abs(np.arange(60)[None, :] - best[:, None]) > radius
    expected = sim.max(axis=1) - np.where(far, sim, -np.inf).max(axis=1)
    np.testing.assert_allclose(got, expected)


def test_a_gate_rejects_whatever_the_score():
    d = decide(parse_acceptance("margin+floor", ["radius=1", "floor:min=0.8"]), Candidates(RETRIEVED, SCORES))
    np.testing.assert_allclose(d.score, [0.4, -np.inf])
    assert d.rule == "margin+floor"
    assert not d.accepted(-1e9)[1]


def test_settings_go_to_the_named_rule_only():
    raw, margin = parse_acceptance_list("raw,margin", ["margin:radius=7"])
    assert raw.settings == {"raw": {}}
    assert margin.settings["margin"]["radius"] == 7
    assert margin.depth == 16


@pytest.mark.parametrize(
    "text, settings, message",
    [
        ("nonsense", [], "unknown acceptance rule 'nonsense'"),
        ("floor", ["floor:min=1"], "is a gate and gives no score"),
        ("margin+ratio", [], "gives a score, not a gate"),
        ("margin", ["radius=-1"], "must be an integer >= 0"),
        ("margin", ["radius=2.5"], "must be an integer >= 0"),
        ("margin", ["radious=2"], "no setting 'radious'"),
        ("margin", ["ratio:radius=2"], "rule 'ratio' is not among"),
        ("margin+floor", [], "floor needs its threshold"),
        ("margin", ["radius"], "expected \\[RULE:\\]KEY=VALUE"),
        ("", [], "no acceptance rule"),
    ],
)
def test_bad_rules_and_settings_are_config_errors(text, settings, message):
    with pytest.raises(ConfigError, match=message):
        parse_acceptance_list(text, settings)


def test_registered_rules_score_and_gate_and_may_choose_another_candidate():
    # a rule that vouches for the second candidate with score 1, and a gate passing even references
    rule = Rule(
        name="second_for_test",
        description="test",
        defaults={"bonus": 0.0},
        score=lambda c, bonus, **_: (np.ones(c.num_queries) + bonus, c.retrieved[:, 1]),
        gate=lambda c, match, **_: match % 2 == 0,
    )
    register_rule(rule)
    try:
        d = decide(parse_acceptance("second_for_test", ["bonus=1"]), Candidates(RETRIEVED, SCORES))
        np.testing.assert_allclose(d.score, [2.0, 2.0])
        np.testing.assert_array_equal(d.match, [6, 9])
        d = decide(parse_acceptance("raw+second_for_test"), Candidates(RETRIEVED, SCORES))
        np.testing.assert_allclose(d.score, [-np.inf, -np.inf])  # 5 and 1 are odd
        with pytest.raises(ValueError, match="already registered"):
            register_rule(Rule(name="second_for_test", description="again", score=lambda c, **_: c.scores[:, 0]))
    finally:
        acceptance._RULES.pop("second_for_test")


def test_a_rule_that_needs_images_refuses_candidates_without_paths():
    register_rule(
        Rule(
            name="looks_for_test", description="test", score=lambda c, **_: c.scores[:, 0], needs=frozenset({"images"})
        )
    )
    try:
        with pytest.raises(ConfigError, match="looks at the images"):
            decide("looks_for_test", Candidates(RETRIEVED, SCORES))
    finally:
        acceptance._RULES.pop("looks_for_test")


def test_bad_candidates_are_data_errors():
    with pytest.raises(DataError, match="one shape"):
        Candidates(RETRIEVED, SCORES[:, :3])
    with pytest.raises(DataError, match="NaN"):
        Candidates(RETRIEVED, np.where(SCORES > 0.8, np.nan, SCORES))


def test_sequence_margin_runs_on_sequence_candidates_and_is_causal():
    """Sequence-consistent margin: the rule on SeqSLAM's candidates; a query's decision never
    depends on later queries (changing them leaves it unchanged)."""
    rng = np.random.default_rng(0)
    queries = rng.normal(size=(30, 8)).astype(np.float32)
    refs = rng.normal(size=(50, 8)).astype(np.float32)
    spec = parse_acceptance("margin", ["radius=2"])
    idx, scores = sequence_top_k(queries, refs, spec.depth, length=5)
    got = decide(spec, Candidates(idx, scores)).score
    seq = sequence_similarity(queries @ refs.T, 5)
    best = seq.argmax(axis=1)
    far = np.abs(np.arange(50)[None, :] - best[:, None]) > 2
    np.testing.assert_allclose(got, seq.max(axis=1) - np.where(far, seq, -np.inf).max(axis=1), rtol=1e-6)
    changed = queries.copy()
    changed[20:] = rng.normal(size=(10, 8))
    idx2, scores2 = sequence_top_k(changed, refs, spec.depth, length=5)
    np.testing.assert_array_equal(decide(spec, Candidates(idx2, scores2)).score[:20], got[:20])
