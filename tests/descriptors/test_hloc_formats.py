"""hloc's global-features HDF5 and retrieval pairs files (fdnet.descriptors.hloc_formats)."""

import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")

from fdnet.descriptors.hloc_formats import (  # noqa: E402
    GlobalFeaturesWriter,
    image_root,
    read_global_features,
    read_pairs,
    relative_names,
    write_global_features,
    write_pairs,
)
from fdnet.errors import DataError, NotAvailableError  # noqa: E402


# hloc's own readers (hloc/utils/io.py, hloc/utils/parsers.py, hloc/pairs_from_retrieval.py), copied
# so the tests check fdnet's files against the code that reads them, without installing hloc.
def hloc_list_h5_names(path):
    names = []
    with h5py.File(str(path), "r", libver="latest") as fd:

        def visit_fn(_, obj):
            if isinstance(obj, h5py.Dataset):
                names.append(obj.parent.name.strip("/"))

        fd.visititems(visit_fn)
    return list(set(names))


def hloc_get_descriptors(names, path, key="global_descriptor"):
    with h5py.File(str(path), "r", libver="latest") as fd:
        desc = [fd[n][key].__array__() for n in names]
    return np.stack(desc, 0).astype(np.float32)


def hloc_parse_retrieval(path):
    retrieval = defaultdict(list)
    with open(path, "r") as f:
        for p in f.read().rstrip("\n").split("\n"):
            if len(p) == 0:
                continue
            q, r = p.split()
            retrieval[q].append(r)
    return dict(retrieval)


NAMES = ["db/0001.jpg", "db/0002.jpg", "query/night/0001.jpg", "top.png", "db/0010.jpg"]


def _vectors(n, dim=7, seed=0):
    vectors = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    vectors[0, 0] = np.float32(1e-42)  # a subnormal: float16 or a text round trip would lose it
    vectors[0, 1] = np.nextafter(np.float32(1), np.float32(2))
    return vectors


def _one_line_naming(exc_info, path):
    message = str(exc_info.value)
    assert "\n" not in message and str(path) in message, message
    return message


def test_global_features_round_trip_is_bit_exact(tmp_path):
    path = tmp_path / "global-feats.h5"
    vectors = _vectors(len(NAMES))
    write_global_features(path, NAMES, vectors)
    names, read = read_global_features(path)
    assert sorted(names) == sorted(NAMES) and read.dtype == np.float32
    by_name = dict(zip(names, read))
    for name, vector in zip(NAMES, vectors):
        assert by_name[name].tobytes() == vector.tobytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["global-feats.h5"]  # no temporary left


def test_the_file_is_hlocs_layout_and_hlocs_readers_read_it(tmp_path):
    path = tmp_path / "global-feats.h5"
    vectors = _vectors(len(NAMES))
    write_global_features(path, NAMES, vectors)
    with h5py.File(path, "r") as f:
        dataset = f["db"]["0001.jpg"]["global_descriptor"]  # nested groups, as create_group makes them
        assert dataset.dtype == np.float32 and dataset.shape == (7,)
        assert isinstance(f["query/night"], h5py.Group)
    assert sorted(hloc_list_h5_names(path)) == sorted(NAMES)
    np.testing.assert_array_equal(hloc_get_descriptors(NAMES, path), vectors)


def test_read_order_is_h5py_visit_order(tmp_path):
    path = tmp_path / "g.h5"
    names = ["db/2.jpg", "a.jpg", "db/10.jpg", "B.jpg", "a/b.jpg"]
    write_global_features(path, names, np.arange(10, dtype=np.float32).reshape(5, 2))
    read, vectors = read_global_features(path)
    # depth first, each group's members in byte order of their names
    assert read == ["B.jpg", "a/b.jpg", "a.jpg", "db/10.jpg", "db/2.jpg"]
    assert vectors[read.index("db/2.jpg")].tolist() == [0, 1]


def test_hlocs_float16_files_read_as_float32(tmp_path):
    """hloc's extract_features stores float16 with as_half (its Python default), plus image_size."""
    path = tmp_path / "hloc.h5"
    with h5py.File(path, "w", libver="latest") as f:
        for i, name in enumerate(["db/a.jpg", "db/b.jpg"]):
            group = f.create_group(name)
            group.create_dataset("global_descriptor", data=np.full(4, i + 0.5, dtype=np.float16))
            group.create_dataset("image_size", data=np.array([640, 480]))
    names, vectors = read_global_features(path)
    assert names == ["db/a.jpg", "db/b.jpg"] and vectors.dtype == np.float32
    assert vectors.tolist() == [[0.5] * 4, [1.5] * 4]


def test_the_writer_streams_batches_and_discards_on_error(tmp_path):
    path = tmp_path / "g.h5"
    vectors = _vectors(10)
    with GlobalFeaturesWriter(path, attrs={"method": "fdnet"}) as writer:
        for start in range(0, 10, 3):
            writer.write([f"f/{i}.png" for i in range(start, min(start + 3, 10))], vectors[start : start + 3])
        assert not path.exists()  # only renamed into place at the end
    names, read = read_global_features(path)
    assert len(names) == 10 and read[names.index("f/9.png")].tobytes() == vectors[9].tobytes()
    with h5py.File(path, "r") as f:
        assert f.attrs["method"] == "fdnet"
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="stop"):
        with GlobalFeaturesWriter(path) as writer:
            writer.write(["x.png"], vectors[:1])
            raise RuntimeError("stop")
    assert path.read_bytes() == before  # the old file untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.h5"]  # and no temporary left


def test_a_killed_writers_folder_is_removed_by_the_next_writer(tmp_path):
    path = tmp_path / "g.h5"
    code = (
        "import os, numpy as np\n"
        "from fdnet.descriptors.hloc_formats import GlobalFeaturesWriter\n"
        f"w = GlobalFeaturesWriter({str(path)!r})\n"
        "w.write(['a.png'], np.ones((1, 3)))\n"
        "os._exit(9)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=False)
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".g.h5.parts.")  # the target was never written
    write_global_features(path, ["b.png"], np.ones((1, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.h5"]


@pytest.mark.parametrize(
    "names, expected",
    [
        (["a.png", "a.png"], "given twice"),
        (["/abs.png"], "absolute"),
        (["db/../x.png"], "'..'"),
        (["db//x.png"], "empty"),
        ([""], "empty image name"),
    ],
)
def test_bad_image_names_are_refused_and_nothing_is_written(tmp_path, names, expected):
    path = tmp_path / "g.h5"
    with pytest.raises(DataError, match=expected) as caught:
        write_global_features(path, names, np.ones((len(names), 2)))
    _one_line_naming(caught, path)
    assert list(tmp_path.iterdir()) == []


def test_a_truncated_file_is_a_data_error_naming_it(tmp_path):
    path = tmp_path / "g.h5"
    write_global_features(path, [f"db/{i}.jpg" for i in range(50)], _vectors(50, dim=64))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="truncated") as caught:
        read_global_features(path)
    _one_line_naming(caught, path)


def test_a_file_that_is_not_hdf5_is_a_data_error(tmp_path):
    path = tmp_path / "g.h5"
    path.write_text("query reference\n")
    with pytest.raises(DataError, match="not an HDF5 file") as caught:
        read_global_features(path)
    _one_line_naming(caught, path)
    with pytest.raises(DataError, match="no such file") as caught:
        read_global_features(tmp_path / "missing.h5")
    _one_line_naming(caught, tmp_path / "missing.h5")


def test_a_local_features_file_or_vectors_of_different_lengths_are_refused(tmp_path):
    local = tmp_path / "feats-superpoint.h5"
    with h5py.File(local, "w") as f:
        f.create_dataset("db/a.jpg/keypoints", data=np.zeros((5, 2), np.float16))
        f.create_dataset("db/a.jpg/descriptors", data=np.zeros((256, 5), np.float16))
    with pytest.raises(DataError, match="no image group holds a 'global_descriptor'") as caught:
        read_global_features(local)
    assert "keypoints" in _one_line_naming(caught, local)
    uneven = tmp_path / "uneven.h5"
    with h5py.File(uneven, "w") as f:
        f.create_dataset("a.jpg/global_descriptor", data=np.zeros(4, np.float32))
        f.create_dataset("b.jpg/global_descriptor", data=np.zeros(5, np.float32))
    with pytest.raises(DataError, match="different lengths") as caught:
        read_global_features(uneven)
    assert "b.jpg" in _one_line_naming(caught, uneven)


def test_a_missing_h5py_says_which_extra_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)  # `import h5py` now raises ImportError
    with pytest.raises(NotAvailableError, match=r"pip install 'fdnet\[hloc\]'"):
        read_global_features(tmp_path / "g.h5")
    with pytest.raises(NotAvailableError, match="h5py"):
        write_global_features(tmp_path / "g.h5", ["a.png"], np.ones((1, 2)))


def test_pairs_round_trip_in_hlocs_exact_format(tmp_path):
    path = tmp_path / "pairs.txt"
    pairs = [("query/0001.jpg", "db/0001.jpg"), ("query/0001.jpg", "db/0002.jpg"), ("query/0002.jpg", "db/0007.jpg")]
    write_pairs(path, iter(pairs))
    # what pairs_from_retrieval writes: one space, "\n" between lines, none after the last
    assert path.read_bytes() == b"query/0001.jpg db/0001.jpg\nquery/0001.jpg db/0002.jpg\nquery/0002.jpg db/0007.jpg"
    assert read_pairs(path) == pairs
    assert hloc_parse_retrieval(path) == {
        "query/0001.jpg": ["db/0001.jpg", "db/0002.jpg"],
        "query/0002.jpg": ["db/0007.jpg"],
    }
    write_pairs(path, [])
    assert path.read_bytes() == b"" and read_pairs(path) == [] and hloc_parse_retrieval(path) == {}


def test_read_pairs_reads_what_hlocs_parser_reads(tmp_path):
    path = tmp_path / "pairs.txt"
    path.write_bytes(b"q1 r1\n\nq1\tr2\r\n#q2 r3\nq2  r4\n\n")  # blank lines, a tab, CRLF, no comments in hloc
    expected = [("q1", "r1"), ("q1", "r2"), ("#q2", "r3"), ("q2", "r4")]
    assert read_pairs(path) == expected
    assert hloc_parse_retrieval(path) == {"q1": ["r1", "r2"], "#q2": ["r3"], "q2": ["r4"]}
    path.write_text("q1 r1\nq2 r2 r3\n")
    with pytest.raises(DataError, match="line 2") as caught:
        read_pairs(path)
    _one_line_naming(caught, path)
    with pytest.raises(ValueError):
        hloc_parse_retrieval(path)  # hloc stops there too


@pytest.mark.parametrize("name", ["my photo.jpg", "a\tb.jpg", "a\nb.jpg", ""])
def test_a_pair_name_hlocs_format_cannot_hold_is_refused(tmp_path, name):
    path = tmp_path / "pairs.txt"
    with pytest.raises(DataError) as caught:
        write_pairs(path, [("q.jpg", "r.jpg"), ("q.jpg", name)])
    message = _one_line_naming(caught, path)
    assert (repr(name) in message) if name else "empty" in message
    assert list(tmp_path.iterdir()) == []


def test_image_root_and_relative_names(tmp_path):
    ref, query = tmp_path / "route" / "summer", tmp_path / "route" / "winter"
    ref.mkdir(parents=True)
    query.mkdir()
    assert image_root([ref, query]) == tmp_path / "route"
    assert image_root([ref, ref]) == ref
    assert relative_names([ref / "a.png", query / "b.png"], tmp_path / "route") == ["summer/a.png", "winter/b.png"]
    video = tmp_path / "route" / "night.mp4"
    video.write_bytes(b"")
    assert image_root([video]) == tmp_path / "route"  # a frame is night.mp4/frame_... below it
    relative = os.path.relpath(ref, Path.cwd())
    assert image_root([relative]) == ref  # made absolute, as listed
    with pytest.raises(DataError, match="not below"):
        relative_names([tmp_path / "elsewhere.png"], ref)


def test_the_attributes_fdnet_records_read_back_and_hlocs_files_have_none(tmp_path):
    from fdnet.descriptors.hloc_formats import read_global_attributes

    path = tmp_path / "fdnet.h5"
    with GlobalFeaturesWriter(path, attrs={"method": "hog", "settings": '{"input_size": [64, 64]}'}) as writer:
        writer.write(["a b/0001.jpg"], _vectors(1))  # a name holding a space: fine in HDF5
    assert read_global_attributes(path) == {"method": "hog", "settings": {"input_size": [64, 64]}}
    assert read_global_features(path)[0] == ["a b/0001.jpg"]
    write_global_features(tmp_path / "hloc.h5", NAMES, _vectors(len(NAMES)))
    assert read_global_attributes(tmp_path / "hloc.h5") == {}
    with h5py.File(tmp_path / "odd.h5", "w") as handle:  # not fdnet's: numbers, a settings that is no dict
        handle.attrs["method"] = 3
        handle.attrs["settings"] = "[1, 2]"
        handle["x.jpg/global_descriptor"] = _vectors(1)[0]
    assert read_global_attributes(tmp_path / "odd.h5") == {}


@pytest.mark.parametrize(
    "case, message",
    [
        ("directory", "not a file"),
        ("empty", "not an HDF5 file"),
        ("lengths", "vectors of different lengths"),
    ],
)
def test_a_global_features_file_that_is_a_folder_empty_or_of_mixed_lengths_is_one_line(case, message, tmp_path):
    path = tmp_path / f"{case}.h5"
    if case == "directory":
        path.mkdir()
    elif case == "empty":
        path.write_bytes(b"")
    else:
        with h5py.File(path, "w") as handle:
            handle["a.jpg/global_descriptor"] = np.ones(4, np.float32)
            handle["b.jpg/global_descriptor"] = np.ones(3, np.float32)
    with pytest.raises(DataError) as caught:
        read_global_features(path)
    assert message in _one_line_naming(caught, path)


FULL_DISK_WRITER = """
import sys
import numpy as np
from fdnet.descriptors.hloc_formats import GlobalFeaturesWriter
from fdnet.errors import OutputError
count, dim = int(sys.argv[2]), int(sys.argv[3])
try:
    with GlobalFeaturesWriter(sys.argv[1]) as writer:
        for i in range(count):
            writer.write([f"db/{i:05d}.jpg"], np.ones((1, dim), np.float32))
except OutputError as exc:
    print(exc)
"""


@pytest.mark.parametrize("count, dim", [(7, 2048), (300, 4), (50, 4)])
def test_a_full_disk_is_one_error_naming_the_file_and_leaves_nothing(small_disk, count, dim):
    """Rows smaller than HDF5's data sieve buffer once met the full disk inside an object's close:
    h5py printed the errors ("Exception ignored") and closing the file crashed the process. Run
    in a child process, so a crash is this test's failure, not the test run's end. (7, 2048): the
    data fails; (300, 4): the metadata while writing; (50, 4): only the final flush."""
    target = small_disk.path / "global-feats.h5"
    small_disk.fill(4096)
    done = subprocess.run(
        [sys.executable, "-c", FULL_DISK_WRITER, str(target), str(count), str(dim)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == f"{target}: cannot write it (no space left on the device); nothing was written there"
    assert done.stderr == "" and small_disk.files() == []


@pytest.mark.parametrize("case", ["external_storage", "virtual", "external_link"])
def test_a_vectors_file_that_reads_other_files_is_refused(case, tmp_path):
    """HDF5 can keep a dataset's bytes in any file (external storage, a virtual dataset, an external
    link): a vectors file pointing at /etc/passwd would give its bytes as a vector."""
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(4, dtype=np.float32).tobytes())
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x.jpg/global_descriptor"] = np.arange(4, dtype=np.float32) + 1
    path = tmp_path / f"{case}.h5"
    with h5py.File(path, "w") as f:
        f["own.jpg/global_descriptor"] = np.ones(4, np.float32)
        if case == "external_storage":
            f.create_dataset("a.jpg/global_descriptor", shape=(4,), dtype="f4", external=[(str(secret), 0, 16)])
        elif case == "virtual":
            layout = h5py.VirtualLayout(shape=(4,), dtype="f4")
            layout[:] = h5py.VirtualSource(str(other), "x.jpg/global_descriptor", shape=(4,))
            f.create_group("a.jpg").create_virtual_dataset("global_descriptor", layout)
        else:
            f.create_group("a.jpg")["global_descriptor"] = h5py.ExternalLink(str(other), "x.jpg/global_descriptor")
    with h5py.File(path, "r") as f:  # HDF5 itself reads the other file's bytes
        assert f["a.jpg/global_descriptor"][()].tolist() in ([0, 1, 2, 3], [1, 2, 3, 4])
    with pytest.raises(DataError, match=rf"{case}\.h5: .*(external|virtual|another file)"):
        read_global_features(path)


def test_a_file_declaring_vectors_it_does_not_hold_is_refused_before_allocating(tmp_path, monkeypatch):
    from fdnet.data import arrays

    path = tmp_path / "claims.h5"
    with h5py.File(path, "w") as f:
        for i in range(3):  # a few KB declaring 3 vectors of a million floats, never written
            f.create_dataset(f"{i}.jpg/global_descriptor", shape=(1_000_000,), dtype="f4", chunks=(100_000,))
    assert path.stat().st_size < 20_000
    with pytest.raises(
        DataError, match=r"claims\.h5: image '0\.jpg': declares a vector of shape \(1000000,\) but " r"holds no data"
    ):
        read_global_features(path)
    written = tmp_path / "written.h5"
    with h5py.File(written, "w") as f:
        for i in range(3):
            f.create_dataset(f"{i}.jpg/global_descriptor", data=np.ones(100_000, np.float32), compression="gzip")
    monkeypatch.setattr(arrays, "physical_memory_bytes", lambda: 1 << 20)  # this process may use 1 MiB
    with pytest.raises(DataError, match=r"written\.h5: 3 vectors of length 100000 need 1\.1 MiB of memory"):
        read_global_features(written)
