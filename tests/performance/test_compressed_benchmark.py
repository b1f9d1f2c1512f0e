"""The compressed-place part of ``fdnet benchmark --parts loop`` on a small map (the 10^7 row is the
benchmark's own run, not a test's)."""

from __future__ import annotations

import numpy as np
import pytest

from fdnet.errors import ConfigError, DataError
from fdnet.performance.benchmark_plan import BenchmarkRequest, plan_benchmark
from fdnet.performance.compressed_benchmark import compressed_rows


def fake_fdnet_vectors(path, places=60, dim=32, seed=0):
    rng = np.random.default_rng(seed)
    ref = rng.standard_normal((places, dim))
    again = ref + 0.3 * rng.standard_normal((places, dim))
    v = np.concatenate([ref, again]).astype(np.float32)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    np.savez(path, v=v, cond=np.repeat([0, 1], places), ids=np.tile(np.arange(places), 2))
    return path


def test_compressed_rows_report_memory_speed_and_agreement(tmp_path):
    sources = [fake_fdnet_vectors(tmp_path / "a.npz"), fake_fdnet_vectors(tmp_path / "b.npz", seed=1)]
    lines = []
    (row,) = compressed_rows([20_000], tmp_path, sources, describe_ms=10.0, log=lines.append)
    assert row["map_size"] == 20_000 and row["queries"] == 120
    assert row["disk_bytes_per_place"] == 128 and row["memory_bytes_per_place"] < 64
    assert 0.9 <= row["same_place"] <= 1 and 0.9 <= row["decision_agreement"] <= 1 and row["recall_at_1"] > 0.9
    assert row["query_ms_median"] <= row["query_ms_p99"] and row["gemv_ms"] > 0 and row["fdnet_frames_per_s"] > 0
    assert row["query_ms_in_blocks"] > 0 and row["blocks_answer_alike"]  # a block's queries in one call: the same
    assert "same decision" in lines[-1]
    assert not list(tmp_path.glob("*.f32"))  # each map's file is deleted after its row


def test_compressed_sizes_need_real_vectors(tmp_path):
    with pytest.raises(ConfigError, match="--loop-compressed-size needs --loop-real-vectors"):
        plan_benchmark(BenchmarkRequest(loop_compressed_size="100000"))
    with pytest.raises(DataError, match="nope.npz: --loop-real-vectors file not found"):
        plan_benchmark(BenchmarkRequest(loop_compressed_size="100000", loop_real_vectors=str(tmp_path / "nope.npz")))
    with pytest.raises(ConfigError, match="start at 10000 places"):
        plan_benchmark(BenchmarkRequest(loop_compressed_size="100", loop_real_vectors="x.npz"))
    plan = plan_benchmark(
        BenchmarkRequest(
            loop_compressed_size="100000,1000000", loop_real_vectors=str(fake_fdnet_vectors(tmp_path / "a.npz"))
        )
    )
    assert plan.loop_compressed_sizes == [100_000, 1_000_000]


def test_the_loop_part_measures_the_detector_through_a_file_database_and_compressed_codes(tmp_path):
    from fdnet.performance.loop_benchmark import DescribeMs, loop_rows

    lines = []
    (row,) = loop_rows(
        [5000],
        dim=32,
        route=30,
        describe_ms=DescribeMs(one=10.0, batch=6.0),
        log=lines.append,
        workdir=str(tmp_path),
        describe_bf16_ms=4.0,
    )
    for search in ("exact", "index", "compressed", "compressed_batched"):
        assert row[f"{search}_ms"] > 0 and row[f"{search}_p99_ms"] >= row[f"{search}_ms"]
        batched = search == "compressed_batched"
        ms = row[f"{search}_mean_ms" if batched else f"{search}_ms"]
        # one image a call where frames come one at a time, the command's batches where they do not
        assert row[f"fdnet_frames_per_s_{search}"] == pytest.approx(1e3 / ((6.0 if batched else 10.0) + ms))
        assert row[f"fdnet_bf16_frames_per_s_{search}"] == pytest.approx(1e3 / (4.0 + ms))
        if search in ("exact", "index"):  # the command: described in batches, decided frame by frame
            assert row[f"fdnet_frames_per_s_{search}_command"] == pytest.approx(1e3 / (6.0 + ms))
    assert row["describe_ms"] == 10.0 and row["describe_batch_ms"] == 6.0
    assert "fp32 (10.0 ms an image one a call, 6.0 in batches)" in lines[-1]
    assert "bf16 (4.0 ms an image one a call, 4.0 in batches)" in lines[-1]
    # revisits lie near their places (noise 0.5): the compressed path finds what the exact one finds
    assert row["compressed_recall_at_1"] == row["exact_recall_at_1"] >= 0.9
    assert row["compressed_agreement"] >= 0.9
    # frames described ahead are searched in blocks: the same decisions as one at a time
    assert row["compressed_batched_agreement"] == row["compressed_agreement"]
    assert row["compressed_batched_recall_at_1"] == row["compressed_recall_at_1"]
    assert "compressed" in lines[-1] and list(tmp_path.iterdir()) == []  # the database and its file are gone
    (small,) = loop_rows([1000], dim=32, route=30, workdir=str(tmp_path))
    assert "compressed_ms" not in small  # below 4096 places there is nothing to compress


def test_a_map_too_large_to_hold_is_streamed_to_the_file_database_and_decided_by_the_compressed_path(
    tmp_path, monkeypatch
):
    from fdnet.performance import loop_benchmark
    from fdnet.performance.timing import random_map, random_map_chunks

    # the chunks are the held map's rows, in order
    assert np.array_equal(np.concatenate(list(random_map_chunks(2500, 8, seed=3, chunk=1000))), random_map(2500, 8, 3))
    monkeypatch.setattr(loop_benchmark, "IN_MEMORY_UP_TO", 4500)
    monkeypatch.setattr(loop_benchmark, "CHUNK", 1000)
    lines = []
    held, streamed = loop_benchmark.loop_rows(
        [4500, 5000], dim=32, route=30, describe_ms=10.0, log=lines.append, workdir=str(tmp_path)
    )
    assert not held["streamed"] and "exact_ms" in held and held["agreement_reference"] == "exact"
    assert streamed["streamed"] and streamed["searches"] == ["compressed", "compressed_batched"]
    assert "exact_ms" not in streamed and "index_ms" not in streamed and streamed["agreement_reference"] == "compressed"
    assert streamed["compressed_recall_at_1"] >= 0.9 and streamed["compressed_batched_agreement"] == 1.0
    assert streamed["gemv_ms"] > 0 and streamed["fdnet_frames_per_s_compressed"] > 0
    assert 0 < streamed["compressed_rss_anon_bytes"] <= streamed["compressed_rss_bytes"]
    assert "compressed_rss_bytes" not in held  # a held map's memory is the map's
    assert "streamed to the file database" in lines[-1] and list(tmp_path.iterdir()) == []
    assert loop_benchmark.loop_rows([5000], dim=32, route=30, log=lines.append) == []  # no folder to stream to
    assert "skipped" in lines[-1]
    # a map the folder has no room for is refused before anything is written
    monkeypatch.setattr(loop_benchmark, "DISK_BYTES_OVER_VECTOR", 10**12)
    with pytest.raises(DataError, match="needs about .* GB of disk there"):
        loop_benchmark.loop_rows([5000], dim=32, route=30, workdir=str(tmp_path))
    assert list(tmp_path.iterdir()) == []


def test_a_failed_compressed_route_closes_its_database_before_its_folder_goes(tmp_path, monkeypatch):
    import os

    from fdnet.decisions.loop_closure import LoopClosureDetector
    from fdnet.performance.loop_benchmark import MapSource, _decide_route

    def fail(*args, **kwargs):
        raise RuntimeError("a frame failed")

    monkeypatch.setattr(LoopClosureDetector, "process_vector", fail)
    vectors = np.random.default_rng(0).standard_normal((5000, 16)).astype(np.float32)
    with pytest.raises(RuntimeError, match="a frame failed"):
        _decide_route(MapSource(5000, 16), vectors, vectors[:3], "compressed", str(tmp_path))
    assert list(tmp_path.iterdir()) == []
    open_files = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            open_files.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # (the listing's own descriptor, closed since)
            pass
    assert not [f for f in open_files if f.startswith(str(tmp_path))]  # no deleted file held open


def test_the_streamed_map_is_written_by_a_process_of_its_own_and_its_failure_is_an_error(tmp_path):
    from fdnet.matching.database import PlaceDatabase
    from fdnet.performance.loop_benchmark import MapSource, StoredVectors, _store_in_a_process_of_its_own

    source = MapSource(3000, 8, streamed=True)
    _store_in_a_process_of_its_own(source, str(tmp_path / "map.db"))
    with PlaceDatabase.open(tmp_path / "map.db", StoredVectors(8)) as db:
        assert len(db) == 3000 and db.names[:2] == ["earlier/0", "earlier/1"]
        np.testing.assert_array_equal(db.vectors, source.array())
    with pytest.raises(DataError, match="storing the benchmark's map failed"):
        _store_in_a_process_of_its_own(source, str(tmp_path / "map.db"))  # it exists: refused there
