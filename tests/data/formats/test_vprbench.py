"""VPR-Bench layout: query/, ref/, ground_truth_new.npy (pickled object rows) or ground_truth.csv."""

import numpy as np
import pytest

from fdnet.data.formats import detect_format, open_split
from fdnet.data.formats.vprbench import load_object_npy
from fdnet.errors import DataError

from .conftest import write_frames
from conftest import require_shared


def make_vprbench(root, n_query=4, n_ref=5):
    write_frames(root / "query", [f"{i:07d}.jpg" for i in range(n_query)])
    write_frames(root / "ref", [f"{i:07d}.jpg" for i in range(n_ref)])
    rows = np.empty((n_query, 2), dtype=object)  # as VPR-Bench saves it
    for q in range(n_query):
        rows[q, 0] = q
        rows[q, 1] = [q, q + 1] if q < n_query - 1 else np.array([4])
    np.save(root / "ground_truth_new.npy", rows)
    return root


def test_npy_ground_truth(tmp_path):
    root = make_vprbench(tmp_path / "ds")
    assert detect_format(root) == "vprbench"
    split = open_split(root)
    assert [p.tolist() for p in split.ground_truth.positives] == [[0, 1], [1, 2], [2, 3], [4]]
    part = open_split(root, split="1:3")
    assert len(part.query) == 2 and len(part.reference) == 5
    assert part.ground_truth.positives[0].tolist() == [1, 2]


def test_npy_loader_refuses_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    arr = np.empty(1, dtype=object)
    arr[0] = Evil()
    path = tmp_path / "ground_truth_new.npy"
    np.save(path, arr)
    with pytest.raises(DataError, match="refusing to load builtins.print"):
        load_object_npy(path)


def test_out_of_range_reference(tmp_path):
    root = make_vprbench(tmp_path / "ds")
    rows = np.empty((1, 2), dtype=object)
    rows[0, 0], rows[0, 1] = 0, [9]
    np.save(root / "ground_truth_new.npy", rows)
    with pytest.raises(DataError, match="reference index 9 out of range"):
        open_split(root)


def test_missing_query_folder(tmp_path):
    root = make_vprbench(tmp_path / "ds")
    for p in (root / "query").iterdir():
        p.unlink()
    (root / "query").rmdir()
    with pytest.raises(DataError, match="query: folder not found"):
        open_split(root, dataset_format="vprbench")


@pytest.mark.shared_data
def test_real_corridor():
    root = require_shared("corridor")
    split = open_split(root)
    assert len(split.query) == len(split.reference) == 111
    assert split.ground_truth.positives[0].tolist() == [0, 1, 2]
    assert split.ground_truth.positives[3].tolist() == [1, 2, 3, 4, 5]
