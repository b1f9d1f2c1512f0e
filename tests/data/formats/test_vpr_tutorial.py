"""VPR_Tutorial layout: two image folders and GT.npz with GThard/GTsoft (database x query)."""

import numpy as np
import pytest

from fdnet.data.formats import detect_format, open_split
from fdnet.errors import DataError

from .conftest import write_frames


def make_stlucia_small(root, n_db=5, n_q=3):
    write_frames(root / "100909_0845", [f"{i:05d}.jpg" for i in range(n_db)])
    write_frames(root / "180809_1545", [f"{i:05d}.jpg" for i in range(n_q)])
    hard = np.zeros((n_db, n_q), bool)
    hard[1, 0] = hard[2, 1] = True  # query 2 has no hard match
    soft = hard.copy()
    soft[3, 2] = soft[2, 0] = True
    np.savez(root / "GT.npz", GThard=hard, GTsoft=soft)
    return root


def test_hard_and_soft(tmp_path):
    root = make_stlucia_small(tmp_path / "StLucia_small")
    assert detect_format(root) == "vpr_tutorial"
    split = open_split(root)
    assert (split.reference.name, split.query.name) == ("100909_0845", "180809_1545")
    assert [p.tolist() for p in split.ground_truth.positives] == [[1], [2], []]
    soft = open_split(root, use_soft="true")
    assert [p.tolist() for p in soft.ground_truth.positives] == [[1, 2], [2], [3]]


def test_wrong_matrix_shape(tmp_path):
    root = make_stlucia_small(tmp_path / "StLucia_small")
    np.savez(root / "GT.npz", GThard=np.zeros((4, 4), bool), GTsoft=np.zeros((4, 4), bool))
    with pytest.raises(DataError, match=r"GThard has shape \(4, 4\) but there are 5 database and 3 query"):
        open_split(root)
