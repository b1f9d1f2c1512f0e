"""The descriptor cache: one entry per (what made the vectors, image list); a changed image, an
unreadable entry or another model is described again."""

from __future__ import annotations

import os

import numpy as np

from fdnet.reproduce.cache import DescriptorCache, image_list_key


def test_image_list_key_follows_the_files(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.write_bytes(b"one")
    b.write_bytes(b"two")
    key = image_list_key([a, b])
    assert image_list_key([a, b]) == key
    assert image_list_key([b, a]) != key
    assert image_list_key([a]) != key
    os.utime(b, ns=(0, 10**9))  # rewritten images change their modification time
    assert image_list_key([a, b]) != key


def test_vectors_are_described_once_per_key(tmp_path):
    cache = DescriptorCache(tmp_path / "cache")
    calls = []

    def describe():
        calls.append(1)
        return np.arange(6, dtype=np.float64).reshape(2, 3)

    parts = {"method": "m", "fingerprint": "f1", "images": "k"}
    first = cache.vectors(parts, describe, label="m/summer")
    again = DescriptorCache(tmp_path / "cache").vectors(parts, describe)
    assert len(calls) == 1 and again.dtype == np.float32
    np.testing.assert_array_equal(first, again)
    cache.vectors({**parts, "fingerprint": "f2"}, describe)  # other weights
    assert len(calls) == 2 and cache.computed == ["m/summer", ""] and cache.hits == 0
    assert not list((tmp_path / "cache").glob(".*.tmp"))


def test_an_unreadable_entry_is_described_again(tmp_path):
    cache = DescriptorCache(tmp_path)
    parts = {"method": "m"}
    cache.vectors(parts, lambda: np.ones((1, 2)))
    cache.path(parts).write_bytes(b"\x93NUMPY broken")
    out = cache.vectors(parts, lambda: np.zeros((1, 2)))
    np.testing.assert_array_equal(out, np.zeros((1, 2)))
    np.testing.assert_array_equal(np.load(cache.path(parts)), np.zeros((1, 2)))


def test_an_entry_holding_nan_is_named_and_described_again(tmp_path, caplog):
    cache = DescriptorCache(tmp_path)
    parts = {"method": "raw", "images": "k"}
    cache.vectors(parts, lambda: np.ones((2, 3)), "raw")
    np.save(cache.path(parts), np.array([[1.0, np.nan, 0.0], [0.0, 1.0, 0.0]], np.float32))
    with caplog.at_level("WARNING"):
        again = cache.vectors(parts, lambda: np.full((2, 3), 2.0), "raw")
    assert np.all(again == 2.0) and cache.computed == ["raw", "raw"]
    assert f"{cache.path(parts)}: cached vectors hold NaN or infinite values" in caplog.text
    assert np.all(np.load(cache.path(parts)) == 2.0)


def test_the_cache_is_kept_under_its_size_cap_removing_what_was_used_longest_ago(tmp_path, monkeypatch):
    import pytest

    from fdnet.errors import ConfigError
    from fdnet.reproduce.cache import cache_cap

    def make(cache, n, vectors):
        return cache.vectors({"set": n}, lambda: vectors, label=f"set {n}")

    one_set = np.ones((64, 64), np.float32)  # 16 KiB of vectors (plus the .npy header)
    first = DescriptorCache(tmp_path)
    for n in range(3):
        make(first, n, one_set)
    for n, age in ((0, 300), (1, 200), (2, 100)):  # set 0 used longest ago
        os.utime(first.path({"set": n}), (1e9 - age, 1e9 - age))
    later = DescriptorCache(tmp_path, max_bytes=3 * 17_000)
    make(later, 3, one_set)  # a fourth set does not fit: the oldest goes, with its .json
    kept = sorted(p.name for p in tmp_path.glob("*.npy"))
    assert len(kept) == 3 and not first.path({"set": 0}).exists()
    assert not first.path({"set": 0}).with_suffix(".json").exists()
    assert all(first.path({"set": n}).exists() for n in (1, 2, 3))
    monkeypatch.setenv("FDNET_CACHE_MAX_MB", "12")
    assert cache_cap() == 12 << 20
    monkeypatch.setenv("FDNET_CACHE_MAX_MB", "lots")
    with pytest.raises(ConfigError, match="FDNET_CACHE_MAX_MB='lots'"):
        cache_cap()
