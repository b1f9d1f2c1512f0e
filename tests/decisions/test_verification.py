"""Geometric verification (fdnet.decisions.verification): a warped copy of a textured image is
verified with many inliers and an unrelated image is not; images too small for local features are
a clear DataError; re-ranking, caching, settings, and the ``verified`` acceptance rule."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from PIL import Image

from fdnet.decisions import Candidates, decide, parse_acceptance, parse_acceptance_list
from fdnet.decisions.verification import (
    FEATURES,
    VerificationSettings,
    Verifier,
    settings_from_overrides,
    verify_candidates,
)
from fdnet.errors import ConfigError, DataError

#: a mild perspective warp (a few degrees of rotation, shift and tilt)
WARP = np.array([[0.95, 0.05, 8.0], [-0.03, 0.97, 5.0], [1e-4, 5e-5, 1.0]])


def textured(seed: int, height: int = 240, width: int = 320) -> np.ndarray:
    """A made scene with many corners: random filled rectangles and discs, RGB uint8."""
    rng = np.random.default_rng(seed)
    img = np.full((height, width), 128, np.uint8)
    for _ in range(120):
        x, y, c = int(rng.integers(0, width)), int(rng.integers(0, height)), int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 40)), y + int(rng.integers(5, 40))), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(3, 20)), c, -1)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)


def warped(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return cv2.warpPerspective(image, WARP, (w, h), borderMode=cv2.BORDER_REFLECT)


def save(path, image: np.ndarray):
    Image.fromarray(image).save(path)
    return path


@pytest.fixture
def scene(tmp_path):
    """query.png, its warped copy and two unrelated images, as files."""
    query = textured(1)
    return {
        "query": save(tmp_path / "query.png", query),
        "warped": save(tmp_path / "warped.png", warped(query)),
        "other": save(tmp_path / "other.png", textured(2)),
        "other2": save(tmp_path / "other2.png", textured(3)),
    }


@pytest.mark.parametrize("features", FEATURES)
@pytest.mark.parametrize("model", ["fundamental", "homography"])
def test_warped_copy_has_many_inliers_unrelated_image_few(scene, features, model):
    verifier = Verifier(VerificationSettings(features=features, model=model))
    inliers = verifier.verify(scene["query"], [scene["warped"], scene["other"], scene["other2"]])
    assert inliers[0] >= 60
    assert inliers[0] >= 5 * max(inliers[1], inliers[2], 1)


def test_default_settings_accept_the_warped_copy_and_reject_the_unrelated_image(scene):
    # the gate's default minimum separates them with the default features and model
    inliers = Verifier().verify(scene["query"], [scene["warped"], scene["other"], scene["other2"]])
    minimum = parse_acceptance("verified").settings["verified"]["min_inliers"]
    assert inliers[0] >= minimum > max(inliers[1], inliers[2])


def test_arrays_and_paths_give_the_same_inliers(scene):
    from_paths = Verifier().verify(scene["query"], [scene["warped"]])
    from_arrays = Verifier().verify(np.asarray(Image.open(scene["query"])), [np.asarray(Image.open(scene["warped"]))])
    float_arrays = Verifier().verify(
        np.asarray(Image.open(scene["query"])) / 255.0, [np.asarray(Image.open(scene["warped"])) / 255.0]
    )
    assert from_paths[0] == from_arrays[0] == float_arrays[0]


def test_each_image_is_described_once_and_each_pair_verified_once(scene):
    verifier = Verifier()
    first = verifier.verify(scene["query"], [scene["warped"], scene["other"]])
    verifier.verify(scene["other"], [scene["warped"], scene["query"]])
    assert verifier.stats["images_described"] == 3
    assert verifier.stats["pairs_verified"] == 4
    again = verifier.verify(scene["query"], [scene["warped"], scene["other"]])
    assert verifier.stats["pairs_verified"] == 4 and verifier.stats["images_described"] == 3
    np.testing.assert_array_equal(first, again)


def test_cache_is_bounded(scene):
    verifier = Verifier(VerificationSettings(cache_size=1))
    verifier.verify(scene["query"], [scene["warped"]])
    verifier.verify(scene["query"], [scene["other"]])  # query was dropped from the cache by then
    assert verifier.stats["images_described"] == 4


@pytest.mark.parametrize("size", [(32, 64), (60, 200)])
def test_too_small_images_are_a_clear_error(tmp_path, scene, size):
    small = save(tmp_path / "thumb.png", np.zeros((*size, 3), np.uint8))
    with pytest.raises(DataError, match=r"thumb\.png: .* too small for geometric verification.*at least 80 pixels"):
        Verifier().verify(small, [scene["warped"]])
    with pytest.raises(DataError, match=r"thumb\.png: .*too small"):
        Verifier().verify(scene["query"], [small])
    with pytest.raises(DataError, match=r"image array: .*too small"):
        Verifier().verify(np.zeros(size, np.uint8), [scene["warped"]])


def test_resizing_below_the_minimum_is_named(scene):
    # 320x240 shrunk to max_side=100 is 100x75: below min_side=80 after resizing
    with pytest.raises(DataError, match=r"320x240 pixels \(resized to 100x75 by max_side=100\)"):
        Verifier(VerificationSettings(max_side=100)).verify(scene["query"], [scene["warped"]])


def test_verify_candidates_reranks_or_only_scores(scene):
    queries = [scene["query"]]
    references = [scene["other"], scene["other2"], scene["warped"]]
    retrieved = np.array([[0, 1, 2]])
    scores = np.array([[0.9, 0.8, 0.7]])
    kept = verify_candidates(queries, references, retrieved, scores, VerificationSettings(rerank=False))
    np.testing.assert_array_equal(kept.retrieved, retrieved)
    assert kept.inliers[0, 2] > kept.inliers[0, 0] and not kept.reranked
    reranked = verify_candidates(queries, references, retrieved, scores, VerificationSettings(rerank=True))
    assert reranked.reranked
    assert reranked.retrieved[0, 0] == 2 and reranked.scores[0, 0] == 0.7
    assert reranked.inliers[0, 0] == kept.inliers[0, 2]
    assert set(reranked.retrieved[0]) == {0, 1, 2}
    assert reranked.timing["verification_pairs"] == 3
    assert reranked.timing["verification_ms_per_query"] > 0


def test_verify_candidates_only_top_k_and_skips_missing_candidates(scene):
    references = [scene["other"], scene["warped"], scene["other2"]]
    result = verify_candidates(
        [scene["query"]],
        references,
        np.array([[-1, 1, 0]]),
        np.array([[0.0, 0.9, 0.8]]),
        VerificationSettings(top_k=2, rerank=True),
    )
    assert result.inliers.shape == (1, 2)
    assert result.retrieved[0, 0] == 1 and result.retrieved[0, 1] == -1  # the missing candidate goes last
    assert result.retrieved[0, 2] == 0  # beyond top_k: untouched
    assert result.timing["verification_pairs"] == 1


def test_verify_candidates_stops_on_thumbnails_before_describing(tmp_path, scene):
    small = save(tmp_path / "images-00010.png", np.zeros((32, 64, 3), np.uint8))
    verifier = Verifier()
    with pytest.raises(DataError, match="images-00010.png: 64x32 pixels"):
        verify_candidates([scene["query"]], [small], np.array([[0]]), np.array([[1.0]]), verifier=verifier)
    assert verifier.stats["images_described"] == 0


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"features": "surf"}, "features='surf': unknown local features; choose one of sift, orb, akaze"),
        ({"model": "affine"}, "model='affine': unknown geometric model"),
        ({"estimator": "lmeds"}, "estimator='lmeds': unknown robust estimator"),
        ({"ratio": "1.5"}, r"ratio=1.5: must be in \(0, 1\]"),
        ({"top_k": "0"}, "top_k=0: must be a whole number >= 1"),
        ({"max_side": "50"}, "min_side=80: is larger than max_side=50"),
        ({"threshold": "-1"}, r"threshold=-1(\.0)?: must be a positive number of pixels"),
        ({"rerank": "maybe"}, "rerank='maybe': must be true or false"),
        ({"colour": "red"}, "verification setting 'colour' is unknown; valid: features"),
    ],
)
def test_bad_settings_are_config_errors(overrides, message):
    with pytest.raises(ConfigError, match=message):
        settings_from_overrides(overrides)


def test_settings_from_overrides_reads_values():
    s = settings_from_overrides(["features=orb", "rerank=true", "ratio=0.7", "model=homography"])
    assert (s.features, s.rerank, s.ratio, s.model) == ("orb", True, 0.7, "homography")


def test_rule_settings_are_checked_when_parsed():
    with pytest.raises(ConfigError, match="features='surf'"):
        parse_acceptance_list("verified", ["verified:features=surf"])
    with pytest.raises(ConfigError, match="min_inliers=-1"):
        parse_acceptance_list("margin+verified", ["verified:min_inliers=-1"])


def test_verified_rule_scores_by_inliers_and_gates_after_plus(scene):
    queries = [scene["query"], scene["other2"]]
    references = [scene["other"], scene["warped"], scene["query"]]
    # query 0: best candidate is the unrelated image, its warped copy second;
    # query 1 (unrelated to every reference): best candidate the warped copy
    candidates = Candidates(
        retrieved=np.array([[0, 1, 2], [1, 0, 2]]),
        scores=np.array([[0.9, 0.8, 0.1], [0.7, 0.6, 0.5]]),
        query_paths=queries,
        reference_paths=references,
    )
    scored = decide(parse_acceptance("verified", ["top_k=2"]), candidates)
    np.testing.assert_array_equal(scored.match, [0, 1])  # descriptor order kept
    assert scored.score[0] < 15 and scored.score[1] < 15
    reranked = decide(parse_acceptance("verified", ["top_k=2", "rerank=true"]), candidates)
    assert reranked.match[0] == 1 and reranked.score[0] >= 60
    gated = decide(
        parse_acceptance("raw+verified"),
        Candidates(
            retrieved=np.array([[1, 0], [1, 0]]),
            scores=np.array([[0.9, 0.1], [0.7, 0.6]]),
            query_paths=queries,
            reference_paths=references,
        ),
    )
    assert gated.score[0] == 0.9 and gated.score[1] == -np.inf


def test_verified_rule_needs_images():
    with pytest.raises(ConfigError, match="looks at the images"):
        decide(parse_acceptance("verified"), Candidates(retrieved=np.array([[0]]), scores=np.array([[1.0]])))


# ---------------------------------------------------------------------------- the CLI path
@pytest.fixture
def textured_route(tmp_path):
    """references: six textured 160x120 scenes; queries: warped copies of the first five, and an
    unrelated scene in place of the sixth (its frame-aligned reference shows something else)."""
    root = tmp_path / "route"
    (root / "map").mkdir(parents=True)
    (root / "moved").mkdir()
    for i in range(6):
        scene = textured(100 + i, 120, 160)
        save(root / "map" / f"{i:03d}.png", scene)
        save(root / "moved" / f"{i:03d}.png", warped(scene) if i < 5 else textured(200, 120, 160))
    return root


def _evaluate(root, *extra):
    return [
        "evaluate",
        "--data",
        str(root),
        "--reference",
        "map",
        "--query",
        "moved",
        "--method",
        "hog",
        "--workers",
        "0",
        *extra,
    ]


def test_cli_evaluate_with_verified_rules(textured_route, tmp_path, capsys):
    import json

    from fdnet.cli import main

    out = tmp_path / "results.json"
    assert (
        main(
            _evaluate(
                textured_route,
                "--accept",
                "verified,margin+verified",
                "--accept-set",
                "margin:radius=0",
                "--json",
                str(out),
            )
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "verified" in printed and "margin+verified" in printed
    result = json.loads(out.read_text())["results"][0]
    assert result["acceptance"] == "verified"
    verified = result["per_acceptance"]["verified"]
    # thresholds of the verified rule are inlier counts: the warped copies have many, and rank first
    assert max(t for t in verified["pr_curve"]["thresholds"] if t is not None) >= 20
    assert verified["recall_at_100_precision"] >= 5 / 6 - 1e-6
    gated = result["per_acceptance"]["margin+verified"]
    # the unrelated sixth query is rejected by the gate whatever its margin: every accepted match is right
    assert gated["precision_at_max_recall"] == 1.0
    assert gated["recall_at_100_precision"] == pytest.approx(5 / 6)
    assert set(result["timing"]["acceptance_ms_per_query"]) == {"verified", "margin+verified"}
    assert result["timing"]["acceptance_ms_per_query"]["verified"] > 0


def test_cli_reranking_by_inliers(textured_route, tmp_path, capsys):
    import json

    from fdnet.cli import main

    out = tmp_path / "results.json"
    assert (
        main(
            _evaluate(
                textured_route,
                "--accept",
                "verified",
                "--accept-set",
                "verified:rerank=true",
                "--accept-set",
                "verified:features=orb",
                "--json",
                str(out),
            )
        )
        == 0
    )
    result = json.loads(out.read_text())["results"][0]
    assert result["acceptance_settings"]["verified"]["rerank"] is True
    assert result["acceptance_settings"]["verified"]["features"] == "orb"
    # re-ranked among the top 5 (all six references here): each warped copy finds its original
    assert max(result["pr_curve"]["recall"]) >= 5 / 6 - 1e-6


@pytest.mark.parametrize(
    "setting, message",
    [
        ("verified:features=surf", "verification setting features='surf': unknown local features"),
        ("verified:ratio=2", r"verification setting ratio=2: must be in (0, 1]"),
        ("verified:min_inliers=-3", "verification setting min_inliers=-3: must be a whole number >= 0"),
        ("verified:colour=red", "no setting 'colour' in rule verified"),
    ],
)
def test_cli_bad_verification_settings(textured_route, capsys, setting, message):
    from fdnet.cli import main

    assert main(_evaluate(textured_route, "--accept", "margin+verified", "--accept-set", setting)) == 2
    err = capsys.readouterr().err
    assert err.startswith("fdnet evaluate: error: ") and message in err and "Traceback" not in err


def test_cli_thumbnails_are_refused_before_describing(tmp_path, capsys, monkeypatch):
    from fdnet.cli import main
    from fdnet.evaluation import experiment

    def never(*args, **kwargs):
        raise AssertionError("images were described before the size check")

    monkeypatch.setattr(experiment, "describe_paths", never)

    root = tmp_path / "thumbs"
    for condition in ("summer", "winter"):
        (root / condition).mkdir(parents=True)
        for i in range(3):
            save(root / condition / f"images-{i:05d}.png", textured(i, 32, 64))
    argv = [
        "evaluate",
        "--data",
        str(root),
        "--reference",
        "summer",
        "--query",
        "winter",
        "--method",
        "hog",
        "--accept",
        "verified",
        "--workers",
        "0",
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "\nfdnet evaluate: error: " in err and "Traceback" not in err
    assert "winter/images-00000.png: 64x32 pixels is too small for geometric verification" in err
    assert "at least 80 pixels" in err


@pytest.mark.parametrize("features", FEATURES)
def test_max_features_bounds_every_detector(scene, features):
    verifier = Verifier(VerificationSettings(features=features, max_features=50))
    assert 0 < len(verifier.features(scene["query"])) <= 50
