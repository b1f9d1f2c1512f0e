""".npy/.npz inputs: headers are checked before anything is allocated; errors name the file."""

from __future__ import annotations

import tracemalloc
import zipfile

import numpy as np
import pytest

from fdnet.data.arrays import load_npy, load_npz_member
from fdnet.errors import DataError

HUGE = (10**6, 10**6)  # float32: 3.6 TiB


def forged_npy_bytes(shape=HUGE, dtype="<f4") -> bytes:
    """A .npy header claiming ``shape`` followed by a few data bytes (what a damaged or hostile
    file looks like), written with numpy's own header writer."""
    import io

    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buffer.getvalue() + b"\0" * 16


def test_forged_header_is_refused_without_allocating(tmp_path):
    path = tmp_path / "forged.npy"
    path.write_bytes(forged_npy_bytes())
    tracemalloc.start()
    try:
        with pytest.raises(DataError) as info:
            load_npy(path, ndim=2, what="similarity matrix")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(info.value)
    assert str(path) in message and "(1000000, 1000000)" in message and "float32" in message
    assert "3.6 TiB" in message and "16 B of data" in message
    assert peak < 10 * 2**20  # numpy reports its allocations to tracemalloc: nothing big was made


def test_memory_limit_and_dimensions(tmp_path):
    path = tmp_path / "m.npy"
    np.save(path, np.zeros((4, 5), np.float32))
    assert load_npy(path, ndim=2).shape == (4, 5)
    with pytest.raises(DataError, match=r"m.npy: shape \(4, 5\) float32 needs 80 B of memory, more than the 64 B"):
        load_npy(path, max_bytes=64)
    with pytest.raises(DataError, match=r"m.npy: expected a 3-D array, but its header says shape \(4, 5\)"):
        load_npy(path, ndim=3)


def test_not_npy_objects_and_missing(tmp_path):
    with pytest.raises(DataError, match="absent.npy: similarity matrix file not found"):
        load_npy(tmp_path / "absent.npy", what="similarity matrix")
    text = tmp_path / "text.npy"
    text.write_text("1,2,3\n")
    with pytest.raises(DataError, match="text.npy: not a .npy file"):
        load_npy(text)
    objects = tmp_path / "objects.npy"
    np.save(objects, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match="objects.npy: holds Python objects"):
        load_npy(objects)


def test_npz_member_with_forged_header_is_refused(tmp_path):
    path = tmp_path / "GT.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("GThard.npy", forged_npy_bytes(dtype="|b1"))
    with pytest.raises(DataError, match=r"GT.npz \(array 'GThard'\): header claims shape \(1000000, 1000000\) bool"):
        load_npz_member(path, "GThard", ndim=2)
    with pytest.raises(DataError, match="has no array 'GTsoft' \\(arrays: GThard\\)"):
        load_npz_member(path, "GTsoft")
    good = tmp_path / "good.npz"
    np.savez(good, GThard=np.eye(3, dtype=bool))
    assert load_npz_member(good, "GThard", ndim=2).tolist() == np.eye(3, dtype=bool).tolist()
