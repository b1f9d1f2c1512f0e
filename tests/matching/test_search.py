"""fdnet.matching.search: exact and indexed ranking, the saved-index cache, the matches CSV."""

from pathlib import Path

import pytest

from fdnet.descriptors import create
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.errors import ConfigError
from fdnet.matching.search import index_settings, map_digest
from fdnet.tasks.match import MatchRequest, match_images

from conftest import read_csv_rows, write_random_places


def make_route(folder, n=12, seed=0, brightness=1.0):
    return write_random_places(folder, n, seed, brightness)


def test_exact_and_indexed_search_find_the_same_places_and_the_index_is_reused(tmp_path):
    ref = make_route(tmp_path / "ref", n=30)
    qry = make_route(tmp_path / "qry", n=30, brightness=0.7)
    messages = []
    for index, out in (("exact", "e.csv"), ("ivf", "i1.csv"), ("ivf", "i2.csv")):
        request = MatchRequest(
            ref,
            qry,
            tmp_path / out,
            top_k=2,
            index=index,
            index_file=None if index == "exact" else tmp_path / "map.index",
            pipeline=PipelineSettings(workers=0, progress=False),
        )
        summary = match_images(request, lambda: create("raw"), log=messages.append)
        assert (summary.num_references, summary.num_queries, summary.method) == (30, 30, "raw")
    exact, first, second = (read_csv_rows(tmp_path / n) for n in ("e.csv", "i1.csv", "i2.csv"))
    assert all(Path(r["query"]).name == Path(r["reference"]).name for r in exact if r["rank"] == "1")
    assert first == second and len(first) == 60
    assert [m.split(" index")[0] for m in messages] == ["built the ivf", "loaded the ivf"]


def test_settings_are_refused_before_the_method_is_made(tmp_path):
    def never():
        raise AssertionError("the descriptor was made before the settings were checked")

    ref = make_route(tmp_path / "ref", n=3)
    for kwargs, message in (
        ({"top_k": 0}, "--top-k"),
        ({"sequence_length": -1}, "--sequence-length"),
        ({"index_set": ["ivf_lists=2"]}, "apply to the faiss indexes"),
        ({"index": "hnsw", "sequence_length": 3}, "use --index exact"),
    ):
        with pytest.raises(ConfigError, match=message):
            match_images(MatchRequest(ref, ref, tmp_path / "m.csv", **kwargs), never)


def test_index_settings_and_the_identity_of_a_map(tmp_path):
    assert index_settings("exact") is None
    assert index_settings("ivf", ["ivf_lists=4"]).ivf_lists == 4
    with pytest.raises(ConfigError, match="--index"):
        index_settings("lsh")
    import os

    # two conditions of one route share file names: they are two maps; so is a rewritten image
    for folder in ("summer", "winter"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "images-00010.png").write_bytes(b"x" * 10)
    summer, winter = tmp_path / "summer" / "images-00010.png", tmp_path / "winter" / "images-00010.png"
    assert map_digest([summer]) != map_digest([winter])
    before = map_digest([summer])
    assert map_digest([summer]) == before
    summer.write_bytes(b"y" * 11)
    rewritten = map_digest([summer])
    assert rewritten != before
    stat = summer.stat()  # the same size, written again later
    os.utime(summer, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert map_digest([summer]) != rewritten
