"""fdnet.descriptors.sharding: one image list described by several torchrun processes.

The parts that need no process group run here in one process; the launches run
``torchrun --standalone --nproc-per-node 2`` (gloo, CPU) on made images and compare with what one
process writes. :func:`torchrun` is shared with tests/cli/test_extract.py and
tests/cli/test_database_command.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

import fdnet
from fdnet.cli import main
from fdnet.descriptors import sharding
from fdnet.descriptors.pipeline import PipelineSettings
from fdnet.descriptors.sharding import KILL_VARIABLE, Shards
from fdnet.errors import ConfigError, DataError

PACKAGE = os.path.dirname(fdnet.__file__)
#: variables of an outer launch that must not reach the one a test starts
LAUNCH_VARIABLES = (
    "WORLD_SIZE",
    "RANK",
    "LOCAL_RANK",
    "LOCAL_WORLD_SIZE",
    "GROUP_RANK",
    "MASTER_ADDR",
    "MASTER_PORT",
    "TORCHELASTIC_RUN_ID",
    KILL_VARIABLE,
)


def torchrun(*args, tmpdir=None, env=None, nproc: int = 2) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc-per-node NPROC -m fdnet ARGS`` on the CPU (one thread per
    process), ``TMPDIR`` set to ``tmpdir`` (where the processes other than rank 0 spool)."""
    environ = {k: v for k, v in os.environ.items() if k not in LAUNCH_VARIABLES}
    environ.update(OMP_NUM_THREADS="1", CUDA_VISIBLE_DEVICES="", **(env or {}))
    if tmpdir is not None:
        tmpdir.mkdir(parents=True, exist_ok=True)
        environ["TMPDIR"] = str(tmpdir)
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc-per-node={nproc}",
        "-m",
        "fdnet",
        *map(str, args),
    ]
    # the timeout only guards against a hang (a process left waiting in a collective)
    return subprocess.run(command, env=environ, capture_output=True, text=True, timeout=300)


def error_lines(result, command: str = "extract") -> list[str]:
    """The command's error lines in a launch's standard error. Two processes write to it at once,
    and a pipe's ``sys.stderr`` writes a line's text and its newline separately, so one process's
    line may run into another's: each starts at its prefix."""
    prefix = f"fdnet {command}: error: "
    text = result.stderr.replace(prefix, "\n" + prefix)
    return [line for line in text.splitlines() if line.startswith(prefix)]


def spools(tmpdir) -> list:
    """The spool files the processes other than rank 0 left in ``tmpdir``."""
    return sorted(tmpdir.glob("fdnet-shards-*/.fdnet-spool.*"))


def images(folder, n: int, seed: int = 0):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):  # natural order: frame_2 before frame_10
        Image.fromarray(rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8)).save(folder / f"frame_{i}.png")
    return folder


# ---------------------------------------------------------------------- one process
@pytest.mark.parametrize("count, world", [(10, 2), (11, 2), (7, 3), (2, 3), (0, 2), (1000, 7)])
def test_blocks_are_contiguous_cover_the_list_in_order_and_differ_by_at_most_one(count, world):
    blocks = [Shards(world, rank).block(count) for rank in range(world)]
    assert blocks[0][0] == 0 and blocks[-1][1] == count
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))
    sizes = [end - start for start, end in blocks]
    assert max(sizes) - min(sizes) <= 1
    assert all(Shards(world, 0).block(count, rank) == blocks[rank] for rank in range(world))


def test_the_environment_says_how_many_processes_and_which_one():
    assert Shards.from_env({}).world_size == 1
    assert Shards.from_env({"WORLD_SIZE": "1", "RANK": "0"}).world_size == 1  # torchrun with one process
    shards = Shards.from_env({"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1", "LOCAL_WORLD_SIZE": "2"})
    assert (shards.world_size, shards.rank, shards.local_rank, shards.is_main) == (4, 3, 1, False)
    assert shards.threads() == max(1, (os.cpu_count() or 1) // 2)
    with pytest.raises(ConfigError, match="RANK is not"):
        Shards.from_env({"WORLD_SIZE": "2"})
    with pytest.raises(ConfigError, match="RANK='x' is not an integer"):
        Shards.from_env({"WORLD_SIZE": "2", "RANK": "x"})
    with pytest.raises(ConfigError, match="invalid torchrun setup"):
        Shards.from_env({"WORLD_SIZE": "2", "RANK": "2"})


def test_one_process_context_changes_nothing():
    shards = Shards()
    assert not shards.enabled and shards.is_main and shards.threads() is None and shards.block(5) == (0, 5)
    assert shards.collectively(lambda: 7) == 7 and shards.collectively(lambda: 8, main_only=True) == 8
    assert shards.any(False) is False and shards.gather(3) == [3] and shards.broadcast("x") == "x"
    shards.stop_if_failed(None)
    with pytest.raises(DataError, match="its own error"):
        shards.stop_if_failed(DataError("its own error"))
    assert sharding.current().world_size == 1
    with sharding.launch({}) as launched:
        assert launched.world_size == 1 and not launched.enabled


def test_one_process_describes_every_batch_in_order(tmp_path):
    from fdnet.data.images import list_images
    from fdnet.descriptors import create

    paths = list_images(images(tmp_path / "images", 11))
    descriptor = create("sad")
    got = []
    sharding.describe_blocks(
        Shards(),
        descriptor,
        paths,
        sharding.BlockOutput([descriptor.dim], lambda start, arrays: got.append((start, arrays[0]))),
        PipelineSettings(batch_size=4, workers=0),
    )
    assert [start for start, _ in got] == [0, 4, 8]
    from fdnet.data.images import load_images

    np.testing.assert_array_equal(
        np.concatenate([a for _, a in got]), descriptor.describe(load_images(paths, descriptor.input_size))
    )


def test_the_kill_hook_names_a_rank_and_a_batch_count():
    assert sharding.kill_after(1, {}) is None
    assert sharding.kill_after(1, {KILL_VARIABLE: "1:3"}) == 3
    assert sharding.kill_after(0, {KILL_VARIABLE: "1:3"}) is None
    with pytest.raises(ConfigError, match="RANK:BATCHES"):
        sharding.kill_after(0, {KILL_VARIABLE: "one"})


def test_commands_that_run_in_one_process_are_refused_under_torchrun():
    sharding.refuse_under_torchrun("fdnet database add", {})
    with pytest.raises(ConfigError, match="fdnet database add runs in one process"):
        sharding.refuse_under_torchrun("fdnet database add", {"WORLD_SIZE": "2", "RANK": "0"})


def test_a_lost_process_is_one_line_without_glooss_source_location():
    from fdnet.torchrun import _backend_message

    message = _backend_message(
        RuntimeError(
            "[/pytorch/third_party/gloo/gloo/transport/tcp/pair.cc:553] Connection closed by peer [127.0.0.1]:61105. "
            "This is typically caused by a remote worker crashing.\nGLHF!"
        )
    )
    assert message == "Connection closed by peer [127.0.0.1]:61105"


def test_extract_and_training_share_the_one_process_group():
    from fdnet.torchrun import ProcessGroup
    from fdnet.training.distributed import DistributedContext

    assert issubclass(Shards, ProcessGroup) and issubclass(DistributedContext, ProcessGroup)
    # each adds no collective of its own: the lockstep is written once
    shared = {"init", "destroy", "agree", "any", "gather", "broadcast", "collectively", "stop_if_failed"}
    assert not shared & (set(vars(Shards)) | set(vars(DistributedContext)))


# ---------------------------------------------------------------------- torchrun, 2 CPU processes
def test_torchrun_h5_and_a_method_learning_on_rank_0_match_one_process(tmp_path):
    """trunk-whitened without --fit learns its whitening from the images: on rank 0, shared with
    rank 1; the hloc .h5 two processes write holds one process's names and vectors."""
    from fdnet.descriptors.hloc_formats import read_global_features

    folder = images(tmp_path / "images", 13)
    common = [
        "extract",
        "--method",
        "trunk-whitened",
        "--method-set",
        "dim=4",
        "--images",
        folder,
        "--fp32",
        "--batch-size",
        "3",
        "--workers",
        "0",
        "--device",
        "cpu",
        "--no-progress",
    ]
    assert main([str(a) for a in common] + ["--out", str(tmp_path / "one.h5")]) == 0
    result = torchrun(*common, "--out", tmp_path / "two.h5", tmpdir=tmp_path / "tmp")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("13 images ->") == 1 and "2 processes" in result.stdout
    assert "learnt from the 13 extracted images" in result.stdout
    names, vectors = read_global_features(tmp_path / "two.h5")
    one_names, one_vectors = read_global_features(tmp_path / "one.h5")
    assert names == one_names
    np.testing.assert_allclose(vectors, one_vectors, atol=1e-5)
    import h5py

    with h5py.File(tmp_path / "two.h5", "r") as f:
        assert json.loads(f.attrs["settings"])["world_size"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "one.h5", "tmp", "two.h5"]
    assert spools(tmp_path / "tmp") == []


def test_torchrun_an_unreadable_image_in_one_block_stops_both_with_one_line_each(tmp_path):
    folder = images(tmp_path / "images", 12)
    (folder / "frame_9.png").write_bytes(b"broken")  # in process 1's block (images 6..11)
    out = tmp_path / "v.npz"
    result = torchrun(
        "extract",
        "--method",
        "sad",
        "--images",
        folder,
        "--out",
        out,
        "--batch-size",
        "2",
        "--workers",
        "1",
        "--no-progress",
        tmpdir=tmp_path / "tmp",
    )
    assert result.returncode != 0
    errors = error_lines(result)
    assert len(errors) == 2 and all("frame_9.png" in e for e in errors), result.stderr
    assert any(e.startswith("fdnet extract: error: stopped because process 1 of 2 failed: ") for e in errors)
    assert PACKAGE not in result.stderr  # no traceback through fdnet's code (torchrun prints its own)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "tmp"]
    assert spools(tmp_path / "tmp") == []


class _TwoProcesses(Shards):
    """Process 0 of 2, with process 1's answers to each exchange given (no process group)."""

    def __init__(self, theirs):
        super().__init__(2, 0)
        self.enabled, self._theirs = True, list(theirs)

    def collectively(self, fn, main_only=False):
        return fn()

    def gather(self, obj):
        return [obj, self._theirs.pop(0)]


def test_processes_given_other_folders_with_the_same_file_names_are_refused(tmp_path):
    """Two conditions of one route share every file name: the processes compare absolute paths,
    sizes and modification times, not names, and name the first image that differs."""
    from fdnet.data.identity import image_facts, images_digest

    a = sorted(images(tmp_path / "A", 3, seed=0).iterdir())
    b = sorted(images(tmp_path / "B", 3, seed=1).iterdir())
    assert [p.name for p in a] == [p.name for p in b]
    descriptor = sharding_descriptor()
    theirs = [(len(b), images_digest(b), descriptor.fingerprint(), descriptor.dim), [image_facts(p) for p in b]]
    with pytest.raises(
        ConfigError,
        match=rf"process 1 of 2 lists other images than process 0: image 0 is " rf"{tmp_path / 'B' / 'frame_0.png'}",
    ):
        sharding.check_same_inputs(_TwoProcesses(theirs), a, descriptor)
    same = [(len(a), images_digest(a), descriptor.fingerprint(), descriptor.dim)]
    sharding.check_same_inputs(_TwoProcesses(same), a, descriptor)  # the same images: accepted


def sharding_descriptor():
    from fdnet.descriptors import create

    return create("sad")


@pytest.mark.parametrize("case", ["symlink", "writable_by_others", "fresh"])
def test_the_spool_folder_in_a_shared_temporary_folder_is_this_users_alone(case, tmp_path, monkeypatch):
    """``TMPDIR/fdnet-shards-UID`` has a predictable name: one made beforehand by someone else (a
    link to their world-writable folder) would receive the spooled vectors."""
    import stat
    import tempfile

    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    folder = tmp_path / f"fdnet-shards-{os.getuid()}"
    trap = tmp_path / "theirs"
    trap.mkdir()
    os.chmod(trap, 0o777)
    if case == "symlink":
        folder.symlink_to(trap)
        with pytest.raises(ConfigError, match="is a symbolic link"):
            sharding._spool_folder()
    elif case == "writable_by_others":
        folder.mkdir()
        os.chmod(folder, 0o777)
        with pytest.raises(ConfigError, match="writable by other users"):
            sharding._spool_folder()
    else:
        assert sharding._spool_folder() == folder
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert list(trap.iterdir()) == []
