"""fdnet.evaluation.splits: the split and similarity matrix evaluate/calibrate score."""

import numpy as np
import pytest
from PIL import Image

from fdnet.errors import ConfigError, DataError
from fdnet.evaluation.splits import build_split, ground_truth_path, load_similarity


def make_folders(root, n=6):
    for condition in ("day", "night"):
        (root / condition).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.full((8, 8, 3), 10 * i, np.uint8)).save(root / condition / f"{i:02d}.png")
    return root


def test_frame_aligned_split_sliced_by_frames(tmp_path):
    split = build_split(make_folders(tmp_path / "d"), "day", "night", frames="1:5", tolerance=1)
    assert len(split.query) == len(split.reference) == 4
    assert split.ground_truth.num_queries == 4


@pytest.mark.parametrize("kwargs,message", [
    ({"frames": "2:60"}, "past the end of the folders"),
    ({"split": "test"}, "need --dataset-format"),
    ({"query": None}, "--reference COND and --query COND"),
])
def test_bad_split_settings_name_the_flag(tmp_path, kwargs, message):
    settings = {"reference": "day", "query": "night", **kwargs}
    with pytest.raises(ConfigError, match=message):
        build_split(make_folders(tmp_path / "d"), settings.pop("reference"), settings.pop("query"), **settings)


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
