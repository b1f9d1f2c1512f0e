"""fdnet.evaluation.splits: the split and similarity matrix evaluate/calibrate score."""

import numpy as np
import pytest
from PIL import Image

from fdnet.errors import ConfigError, DataError
from fdnet.evaluation.splits import SplitSpec, build_split, ground_truth_path, load_similarity


def make_folders(root, n=6):
    for condition in ("day", "night"):
        (root / condition).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.full((8, 8, 3), 10 * i, np.uint8)).save(root / condition / f"{i:02d}.png")
    return root


def test_frame_aligned_split_sliced_by_frames(tmp_path):
    split = build_split(SplitSpec(make_folders(tmp_path / "d"), "day", "night", frames="1:5", tolerance=1))
    assert len(split.query) == len(split.reference) == 4
    assert split.ground_truth.num_queries == 4


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"frames": "2:60"}, "past the end of the folders"),
        ({"split": "test"}, "need --dataset-format"),
        ({"query": None}, "--reference COND and --query COND"),
    ],
)
def test_bad_split_settings_name_the_flag(tmp_path, kwargs, message):
    settings = {"reference": "day", "query": "night", **kwargs}
    with pytest.raises(ConfigError, match=message):
        build_split(
            SplitSpec(make_folders(tmp_path / "d"), settings.pop("reference"), settings.pop("query"), **settings)
        )


def test_similarity_files(tmp_path):
    np.save(tmp_path / "s.npy", np.array([[1.0, 2.0], [3.0, 4.0]]))
    assert load_similarity(tmp_path / "s.npy", distance=True)[1, 1] == -4.0
    np.save(tmp_path / "bad.npy", np.array([[1.0, np.nan]]))
    with pytest.raises(DataError, match="NaN or infinite"):
        load_similarity(tmp_path / "bad.npy")
    with pytest.raises(DataError, match="ground-truth file not found"):
        ground_truth_path(tmp_path / "missing.csv")
    assert ground_truth_path(None) is None


def test_a_similarity_file_is_scored_against_a_ground_truth_csv(tmp_path):
    from fdnet.evaluation.splits import evaluate_similarity_file

    np.save(tmp_path / "run_similarity.npy", np.eye(3) + 0.1)
    (tmp_path / "gt.csv").write_text("query_index,reference_indices\n0,0\n1,1\n2,2\n")
    result = evaluate_similarity_file(tmp_path / "run_similarity.npy", ground_truth=tmp_path / "gt.csv")
    assert result.method == "run" and result.metrics["recall-over-queries"].recall_at_n[1] == 1.0
    (tmp_path / "gt4.csv").write_text("query_index,reference_indices\n0,0\n1,1\n2,2\n3,3\n")
    with pytest.raises(DataError, match="out of range"):
        evaluate_similarity_file(tmp_path / "run_similarity.npy", ground_truth=tmp_path / "gt4.csv")
    with pytest.raises(ConfigError, match="needs ground truth"):
        evaluate_similarity_file(tmp_path / "run_similarity.npy")


def test_a_published_layout_is_not_read_as_plain_folders_without_a_word(tmp_path, caplog):
    """A VPR-Bench folder (query/, ref/, ground_truth.csv) read as plain folders would match
    query i only to reference i and ignore its ground truth: refused, naming the format."""
    root = tmp_path / "corridor"
    for condition in ("query", "ref"):
        (root / condition).mkdir(parents=True)
        for i in range(4):
            Image.fromarray(np.full((8, 8, 3), 40 * i, np.uint8)).save(root / condition / f"{i:03d}.png")
    (root / "ground_truth.csv").write_text("query_index,reference_indices\n0,1\n1,2\n2,3\n3,0\n")
    with pytest.raises(ConfigError, match="'vprbench' dataset format, which carries its own ground truth"):
        build_split(SplitSpec(root, "ref", "query"))
    # said on purpose: frame alignment; or the format's own ground truth
    assert build_split(SplitSpec(root, "ref", "query", tolerance=0)).ground_truth.positives[3].tolist() == [3]
    assert build_split(SplitSpec(root, dataset_format="auto")).ground_truth.positives[3].tolist() == [0]


def test_the_tolerance_in_use_is_said_and_gardens_point_gets_its_protocol(tmp_path, caplog):
    root = tmp_path / "gardens_point"
    for condition in ("day_right", "night_right"):
        (root / condition).mkdir(parents=True)
        for i in range(8):
            Image.fromarray(np.full((8, 8, 3), 20 * i, np.uint8)).save(root / condition / f"Image{i:03d}.jpg")
    split = build_split(SplitSpec(root, "day_right", "night_right"))
    assert split.ground_truth.positives[4].tolist() == [2, 3, 4, 5, 6]
    # the description every command prints names the tolerance and where it came from
    assert split.description == (
        "gardens_point: night_right -> day_right, frame-aligned, tolerance 2 frames "
        "(Gardens Point's protocol, as VPR-Bench; --tolerance changes it)"
    )
    exact = build_split(SplitSpec(root, "day_right", "night_right", tolerance=0))
    assert exact.ground_truth.positives[4].tolist() == [4] and "protocol" not in exact.description
    own = build_split(SplitSpec(make_folders(tmp_path / "own"), "day", "night"))
    assert "frame-aligned, tolerance 0 frames" in own.description
