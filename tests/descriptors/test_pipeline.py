"""The streaming pipeline: batches in order from DataLoader workers, errors
named in the main process, vectors written in chunks, and memory bounded far below a folder's
decoded size."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fdnet.data.images import load_image, load_image_uint8
from fdnet.descriptors.base import Descriptor, describe_paths
from fdnet.descriptors.pipeline import (
    NpzChunkWriter,
    PipelineSettings,
    VectorSpool,
    describe_stream,
    iter_image_batches,
)
from fdnet.errors import DataError

REPO = Path(__file__).resolve().parents[2]


def make_folder(folder: Path, n: int, size=(12, 16), seed=0) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        path = folder / f"frame_{i:05d}.png"
        Image.fromarray(rng.integers(0, 256, size=(*size, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


class MeanColour(Descriptor):
    """Per-image mean of each channel: cheap, so the test measures the pipeline."""

    name = "mean-colour"

    def __init__(self, input_size=(24, 32), uint8=False):
        self.input_size = input_size
        self.accepts_uint8 = uint8

    @property
    def dim(self) -> int:
        return 3

    def describe(self, images):
        return np.asarray(images, dtype=np.float32).reshape(len(images), -1, 3).mean(axis=1)


@pytest.mark.parametrize("workers", [0, 2])
@pytest.mark.parametrize("uint8", [False, True])
def test_batches_come_in_order_with_the_loaders_values(tmp_path, workers, uint8):
    paths = make_folder(tmp_path / "f", 23)
    seen = []
    for start, batch in iter_image_batches(paths, (6, 8), batch_size=5, uint8=uint8, workers=workers):
        assert batch.dtype == (np.uint8 if uint8 else np.float32) and batch.shape[1:] == (6, 8, 3)
        loader = load_image_uint8 if uint8 else load_image
        for i, image in enumerate(batch):
            np.testing.assert_array_equal(image, loader(paths[start + i], (6, 8)))
        seen.append((start, len(batch)))
    assert seen == [(0, 5), (5, 5), (10, 5), (15, 5), (20, 3)]


@pytest.mark.parametrize("workers", [0, 1])
def test_describe_paths_equals_describing_all_images_at_once(tmp_path, workers):
    paths = make_folder(tmp_path / "f", 40)
    d = MeanColour()
    timing = {}
    streamed = describe_paths(d, paths, batch_size=7, timing=timing, workers=workers, progress=True)
    from fdnet.data.images import load_images

    np.testing.assert_allclose(streamed, d.describe(load_images(paths, d.input_size)), rtol=1e-6)
    assert timing["num_images"] == 40 and timing["seconds_describe"] > 0
    assert describe_paths(d, [], workers=workers).shape == (0, 3)


@pytest.mark.parametrize("workers", [0, 2])
def test_an_unreadable_image_is_a_data_error_naming_it(tmp_path, workers):
    paths = make_folder(tmp_path / "f", 12)
    paths[9].write_bytes(b"not an image")
    with pytest.raises(DataError) as info:
        list(describe_stream(MeanColour(), paths, PipelineSettings(batch_size=4, workers=workers)))
    assert str(paths[9]) in str(info.value) and "Traceback" not in str(info.value)


def test_npz_chunk_writer_is_an_ordinary_npz_and_atomic(tmp_path):
    out = tmp_path / "v.npz"
    rows = np.arange(30, dtype=np.float32).reshape(10, 3)
    with NpzChunkWriter(out, {"a": ((10, 3), np.float32), "b": ((10, 3), np.float32)}) as writer:
        for start in range(0, 10, 4):
            writer.write("a", rows[start : start + 4])
            writer.write("b", -rows[start : start + 4])
        writer.close({"names": np.array([f"n{i}" for i in range(10)])})
    with np.load(out, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["a"], rows)
        np.testing.assert_array_equal(z["b"], -rows)
        assert list(z["names"][:2]) == ["n0", "n1"]
    # an incomplete array is refused and the existing target is left as it was
    before = out.read_bytes()
    writer = NpzChunkWriter(out, {"a": ((10, 3), np.float32)})
    writer.write("a", rows[:4])
    with pytest.raises(ValueError, match="4 rows written of 10"):
        writer.close()
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["v.npz"]  # no parts left behind


def test_vector_spool_round_trip(tmp_path):
    rows = np.random.default_rng(0).normal(size=(25, 4)).astype(np.float32)
    with VectorSpool(tmp_path, 4) as spool:
        spool.write(rows[:10])
        spool.write(rows[10:])
        back = list(spool.chunks(rows_per_chunk=7))
        path = spool.path
    assert [s for s, _ in back] == [0, 7, 14, 21]
    np.testing.assert_array_equal(np.concatenate([c for _, c in back]), rows)
    assert not path.exists()


# ------------------------------------------------------------------ bounded memory
MEMORY_SCRIPT = textwrap.dedent("""
    import json, resource, sys
    import numpy as np
    sys.path.insert(0, sys.argv[3])
    from test_pipeline import MeanColour
    from fdnet.data.images import list_images
    from fdnet.descriptors.base import describe_paths

    workers = int(sys.argv[2])
    paths = list_images(sys.argv[1])
    d = MeanColour(input_size=(512, 512))          # 3 MB per decoded float32 image
    describe_paths(d, paths[:16], batch_size=8, workers=0)  # warm up imports and allocators
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    vectors = describe_paths(d, paths, batch_size=8, workers=workers)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    print(json.dumps({"base": base, "peak": peak, "children": children, "rows": len(vectors),
                      "decoded": len(paths) * 512 * 512 * 3 * 4}))
""")


@pytest.mark.parametrize("workers", [0, 1])
def test_a_folder_streams_in_memory_far_below_its_decoded_size(tmp_path, workers):
    """700 images decode to 2.2 GB of float32 at 512x512; describing them through the pipeline
    must not grow the process (nor a decoding worker) by more than 300 MB, a seventh of that.
    Holding every image (as loading the folder at once would) fails this by 1.9 GB."""
    folder = tmp_path / "big"
    make_folder(folder, 700, size=(16, 16))
    script = tmp_path / "measure.py"
    script.write_text(MEMORY_SCRIPT)
    done = subprocess.run(
        [sys.executable, str(script), str(folder), str(workers), str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    m = json.loads(done.stdout.strip().splitlines()[-1])
    cap = 300 * 2**20
    assert m["rows"] == 700 and m["decoded"] > 6 * cap
    assert m["peak"] - m["base"] < cap, m
    if workers:
        assert m["children"] < m["base"] + cap, m


_SPOOL_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from fdnet.descriptors.pipeline import VectorSpool
    spool = VectorSpool(sys.argv[1], 4)
    spool.write(np.ones((3, 4), np.float32))
    print(spool.path, flush=True)
    time.sleep(60)
""")


def _spool_writer(folder):
    """A process holding a spool in ``folder`` (as `database add` does while describing)."""
    writer = subprocess.Popen([sys.executable, "-c", _SPOOL_WRITER, str(folder)], stdout=subprocess.PIPE, text=True)
    return writer, Path(writer.stdout.readline().strip())


@pytest.mark.skipif(sys.platform == "win32", reason="spools are swept with flock, which Windows lacks")
def test_spools_of_killed_writers_are_removed_by_the_next_and_live_ones_kept(tmp_path):
    from fdnet.descriptors.pipeline import VectorSpool

    killed, stale = _spool_writer(tmp_path)
    alive, live = _spool_writer(tmp_path)
    try:
        killed.kill()  # SIGKILL: no cleanup runs, the spool stays behind
        killed.wait()
        assert stale.exists() and live.exists()
        with VectorSpool(tmp_path, 4) as spool:
            assert not stale.exists()  # no process held it: removed
            assert live.exists()  # its writer is still describing: kept
            assert spool.path.exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == [live.name]
    finally:
        alive.kill()
        alive.wait()


_NPZ_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from fdnet.descriptors.pipeline import NpzChunkWriter
    writer = NpzChunkWriter(sys.argv[1], {"v": ((4, 2), np.float32)})
    writer.write("v", np.ones((2, 2), np.float32))
    print(writer._folder, flush=True)
    time.sleep(60)
""")


@pytest.mark.skipif(sys.platform == "win32", reason="parts folders are swept with flock, which Windows lacks")
def test_parts_of_a_killed_npz_writer_are_removed_by_the_next_writer_of_that_file(tmp_path):
    from fdnet.descriptors.pipeline import NpzChunkWriter

    target = tmp_path / "vectors.npz"
    started = [
        subprocess.Popen([sys.executable, "-c", _NPZ_WRITER, str(target)], stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    killed, alive = started
    parts = [Path(p.stdout.readline().strip()) for p in started]
    try:
        killed.kill()  # kill -9 of `fdnet extract`: its parts folder stays
        killed.wait()
        assert all(p.is_dir() for p in parts)
        with NpzChunkWriter(target, {"v": ((1, 2), np.float32)}) as writer:
            writer.write("v", np.zeros((1, 2), np.float32))
            writer.close()
        assert not parts[0].exists() and parts[1].is_dir()  # the live writer's folder is kept
        assert np.load(target)["v"].tolist() == [[0.0, 0.0]]
    finally:
        alive.kill()
        alive.wait()


@pytest.mark.parametrize(
    "batch_size, workers, message",
    [(0, None, "--batch-size must be >= 1, got 0"), (64, -1, "--workers must be >= 0, got -1")],
)
def test_pipeline_settings_out_of_range_are_refused(batch_size, workers, message):
    from fdnet.descriptors.pipeline import check_pipeline_settings
    from fdnet.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        check_pipeline_settings(batch_size, workers)
    check_pipeline_settings(1, 0)  # the smallest allowed
    check_pipeline_settings(None, None)  # defaults


def test_a_worker_that_cannot_hand_its_batch_over_is_one_line_not_a_hang(tmp_path):
    """Under a file size limit (and with a small /dev/shm), a decoding worker could not put its
    batch in shared memory: two tracebacks and the main process waited forever. Batches now come
    back as arrays through the pipe; the command ends with one line on what it could not write."""
    import subprocess
    import sys

    resource = pytest.importorskip("resource", reason="RLIMIT_FSIZE needs a POSIX system")
    from conftest import write_random_places

    images = write_random_places(tmp_path / "images", 40)

    def limit():
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, resource.RLIM_INFINITY))

    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "fdnet",
            "extract",
            "--method",
            "raw",
            "--images",
            str(images),
            "--out",
            str(tmp_path / "v.npz"),
            "--workers",
            "1",
            "--batch-size",
            "8",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=limit,
    )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("fdnet extract: error: ")


def _state(pid: int) -> str | None:
    """A process's state letter from /proc (None when it is gone; 'Z' for a zombie: dead)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except (OSError, IndexError):
        return None


def _children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads processes from /proc (Linux)")
def test_decoding_workers_die_with_their_parent_whatever_kills_it(tmp_path):
    """kill -9 of a command left a decoding worker alive for good, blocked writing a batch nobody
    would read (its parent PID 1). Workers now die with the process that started them."""
    import os
    import signal
    import time

    make_folder(tmp_path / "images", 12, size=(256, 256))
    # batches of 256x256 float32 images: each is larger than a pipe holds, so a worker whose
    # parent stopped reading blocks on the pipe (as the user's did)
    script = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        from fdnet.descriptors.pipeline import iter_image_batches
        paths = sorted(Path({str(tmp_path / 'images')!r}).iterdir())
        batches = iter_image_batches(paths, (256, 256), batch_size=2, workers=2)
        next(batches)
        print("ready", flush=True)
        time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert parent.stdout.readline().strip() == "ready"
        workers = _children(parent.pid)
        assert len(workers) == 2, workers
        time.sleep(1)  # the workers fill their queue and block on the pipe
    finally:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
    # wait for the workers to go (at once with the fix; never without: a wait, not a timing)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and any(_state(pid) not in (None, "Z") for pid in workers):
        time.sleep(0.2)
    alive = [pid for pid in workers if _state(pid) not in (None, "Z")]
    for pid in alive:  # leave nothing behind, then fail
        os.kill(pid, signal.SIGKILL)
    assert not alive, f"decoding workers {alive} outlived their killed parent"
