"""fdnet.performance.benchmark: the settings are checked before anything is measured, and the
tables go to the ``out`` callable (library code never prints)."""

import pytest

from fdnet.errors import ConfigError
from fdnet.performance.benchmark import run_benchmark
from fdnet.performance.benchmark_plan import BenchmarkRequest, plan_benchmark


def test_plan_parses_the_command_spellings():
    plan = plan_benchmark(
        BenchmarkRequest(
            parts="scale, methods",
            checkpoints=("fdnet:run",),
            map_size="100,2000",
            indexes="flat,hnsw",
            index_set=("hnsw:hnsw_neighbors=8",),
            sweep=("hnsw_ef_search=8,16",),
            lengths="256,512",
            quick=True,
            threads=1,
            device="CPU",
        )
    )
    assert plan.parts == ["scale", "methods"] and plan.checkpoints == {"fdnet": "run"}
    assert plan.map_sizes == [100, 2000] and plan.kinds == ["flat", "hnsw"] and plan.lengths == [256, 512]
    assert plan.overrides == {"hnsw": {"hnsw_neighbors": 8}} and plan.sweep == {"hnsw_ef_search": [8, 16]}
    assert plan.device == "cpu" and plan.repeats == 2


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"parts": "scale,nothing"}, "--parts"),
        ({"map_size": "1"}, "at least 2 places"),
        ({"lengths": "big"}, "--lengths"),
        ({"checkpoints": ("run",)}, "METHOD:RUN_DIR"),
        ({"query_vectors": None, "noise": -1.0}, "--noise"),
    ],
)
def test_plan_refuses_bad_settings(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        plan_benchmark(BenchmarkRequest(**kwargs))


def test_scale_part_writes_its_table_to_out_and_returns_rows():
    lines = []
    plan = plan_benchmark(
        BenchmarkRequest(
            parts="scale", map_size="300", indexes="flat", queries=20, scale_dim=8, threads=1, quick=True, device="cpu"
        )
    )
    report = run_benchmark(plan, out=lines.append)
    assert [(r["map_size"], r["index"], r["dim"]) for r in report["scale"]] == [(300, "flat", 8)]
    assert report["scale"][0]["recall_at_1"] == 1.0
    assert any("Scale: a map of 300 random unit 8-d vectors" in line for line in lines)
    assert lines[0].startswith("fdnet benchmark: 1 threads")


def test_a_benchmark_stopped_with_sigterm_removes_its_scratch_folder(tmp_path):
    # the loop part's maps live there: tens of GB at 10^7 places must not outlive a killed run
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    src = str(Path(__file__).resolve().parents[2] / "src")
    env = dict(os.environ, TMPDIR=str(tmp_path), PYTHONPATH=src)
    proc = subprocess.Popen(
        [sys.executable, "-m", "fdnet", "benchmark", "--parts", "loop", "--loop-map-size", "200000", "--threads", "1"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob("fdnet-benchmark-*/fdnet-loop-map-*")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        proc.wait()
    assert list(tmp_path.iterdir()) == []


def test_release_free_heap_returns_what_the_allocator_kept(monkeypatch):
    import ctypes
    import sys

    from fdnet.performance.timing import process_memory, release_free_heap

    if not sys.platform.startswith("linux") or "RssAnon" not in process_memory():
        pytest.skip("needs Linux's /proc/self/status")
    try:
        ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        pytest.skip("no glibc malloc_trim here")
    # 200 MB in blocks malloc serves from its heap, 9 of 10 freed: the heap keeps the holes
    blocks = [bytes(bytearray(2000)) for _ in range(100_000)]
    kept = blocks[::10]
    del blocks
    before = process_memory()["RssAnon"]
    release_free_heap()
    after = process_memory()["RssAnon"]
    assert before - after > 100e6, (before, after)
    assert len(kept) == 10_000
    # without glibc it does nothing, and says nothing
    monkeypatch.setattr(ctypes, "CDLL", lambda name: (_ for _ in ()).throw(OSError(name)))
    release_free_heap()
