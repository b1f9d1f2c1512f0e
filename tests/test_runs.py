"""Crash-safe run directories (fdnet.runs): what a reader finds after kill -9, a full disk, a
second training into the same folder, and what is not a run."""

from __future__ import annotations

import builtins
import errno
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch
import yaml

from fdnet import runs
from fdnet.config import to_dict
from fdnet.errors import ConfigError, OutputError
from fdnet.runs import checkpoints


def list_checkpoints(run_dir) -> list[Path]:
    """Published generation folders of ``run_dir``, newest first, complete or not (what a reader
    chooses from; only these tests need the whole list)."""
    return [g.path for g in checkpoints._generations(Path(run_dir) / runs.CHECKPOINTS_DIR)]


SRC = Path(__file__).resolve().parents[1] / "src"


@dataclass
class _Net:
    width: int = 4


@dataclass
class _Cfg:
    net: _Net = field(default_factory=_Net)
    lr: float = 1e-3
    step: int = 0


def _model(width=4):
    return torch.nn.Sequential(torch.nn.Linear(3, width), torch.nn.BatchNorm1d(width))


def _trained(seed=0, width=4):
    """A model and an Adam optimiser with non-trivial state."""
    torch.manual_seed(seed)
    model = _model(width)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    model(torch.randn(5, 3)).sum().backward()
    optimizer.step()
    return model, optimizer


def _filled(model, value):
    with torch.no_grad():
        for tensor in model.state_dict().values():
            if tensor.is_floating_point():
                tensor.fill_(value)
    return model


def _value_of(model) -> float:
    """The single value every float tensor of ``model`` holds (fails if they differ)."""
    values = torch.unique(torch.cat([t.flatten() for t in model.state_dict().values() if t.is_floating_point()]))
    assert len(values) == 1, f"weights from more than one save: {values[:5].tolist()}"
    return float(values[0])


def _save(run_dir, step, keep=2, width=4):
    model = _filled(_model(width), step)
    optimizer = torch.optim.SGD(model.parameters(), lr=float(step))
    return runs.save_checkpoint(
        run_dir,
        {"net": model},
        _Cfg(step=step),
        optimizers={"opt": optimizer},
        state={"step": step, "marker": torch.full((3,), float(step))},
        keep=keep,
    )


def _assert_current_step(run_dir, step, width=4):
    """Weights, training state (incl. optimiser) and config of the current checkpoint all say ``step``."""
    model = _model(width)
    optimizer = torch.optim.SGD(model.parameters(), lr=12345.0)
    metadata = runs.load_weights(run_dir, {"net": model})
    state = runs.load_training_state(run_dir, {"opt": optimizer})
    config = runs.load_config(run_dir, _Cfg)
    assert int(metadata["step"]) == step
    assert _value_of(model) == step
    assert state["step"] == step and torch.equal(state["marker"], torch.full((3,), float(step)))
    assert optimizer.param_groups[0]["lr"] == step
    assert config.step == step


def _leftovers(run_dir):
    return sorted(p.name for p in Path(run_dir).rglob(".tmp-*"))


# ---------------------------------------------------------------------------- round trip


def test_round_trip_is_bit_exact_and_the_second_save_wins(tmp_path):
    model, optimizer = _trained(0)
    rng = torch.get_rng_state()
    runs.save_checkpoint(tmp_path, {"net": model}, _Cfg(), optimizers={"opt": optimizer}, state={"step": 7, "rng": rng})
    newer, newer_optimizer = _trained(1)
    runs.save_checkpoint(
        tmp_path, {"net": newer}, _Cfg(lr=0.5), optimizers={"opt": newer_optimizer}, state={"step": 8, "rng": rng}
    )

    other, other_optimizer = _trained(2)
    metadata = runs.load_weights(tmp_path, {"net": other})
    assert metadata["step"] == "8"
    for key, value in newer.state_dict().items():
        assert torch.equal(value, other.state_dict()[key]), key
    state = runs.load_training_state(tmp_path, {"opt": other_optimizer})
    assert state["step"] == 8 and torch.equal(state["rng"], rng)
    assert torch.equal(
        newer_optimizer.state_dict()["state"][0]["exp_avg"], other_optimizer.state_dict()["state"][0]["exp_avg"]
    )
    assert runs.load_config(tmp_path, _Cfg) == _Cfg(lr=0.5)
    assert runs.is_run(tmp_path)


def test_keep_prunes_the_oldest_only_after_publishing(tmp_path):
    for step in (100, 200, 300):
        published = _save(tmp_path, step, keep=2)
    assert published == runs.latest_checkpoint(tmp_path)
    names = [p.name for p in list_checkpoints(tmp_path)]
    assert names == ["step-000000300", "step-000000200"]
    _assert_current_step(tmp_path, 300)
    # The one before the current stays readable as a complete unit.
    _assert_current_step(tmp_path / runs.CHECKPOINTS_DIR / "step-000000200", 200)
    assert _leftovers(tmp_path) == []


def test_same_step_saved_again_replaces_the_old_one(tmp_path):
    _save(tmp_path, 5)
    first = runs.latest_checkpoint(tmp_path)
    model = _filled(_model(), 55)
    runs.save_checkpoint(tmp_path, {"net": model}, _Cfg(step=5), state={"step": 5})
    assert runs.latest_checkpoint(tmp_path) != first and not first.exists()
    assert [int(runs.load_weights(p, {"net": _model()})["step"]) for p in list_checkpoints(tmp_path)] == [5]
    check = _model()
    runs.load_weights(tmp_path, {"net": check})
    assert _value_of(check) == 55


def test_a_save_after_resuming_from_an_earlier_step_becomes_current(tmp_path):
    # Generations of later steps are an abandoned history (the run went on from an earlier one);
    # left in place they would be taken as "newest" by the next resume.
    for step in (1, 2, 3):
        _save(tmp_path, step, keep=3)
    _save(tmp_path, 2, keep=3)
    _assert_current_step(tmp_path, 2)
    assert runs.latest_checkpoint(tmp_path).name.startswith("step-000000002")


def test_best_weights_only_checkpoint(tmp_path):
    model, _ = _trained(0)
    best = tmp_path / "best"
    runs.save_weights(best, {"net": model}, _Cfg(), step=40)
    other = _model()
    assert runs.load_weights(best, {"net": other})["step"] == "40"
    assert torch.equal(other[0].weight, model[0].weight)
    assert runs.load_config(best, _Cfg) == _Cfg()
    with pytest.raises(ConfigError, match="weights-only checkpoint.*cannot be resumed"):
        runs.load_training_state(best)
    runs.save_weights(best, {"net": _filled(_model(), 3.0)}, _Cfg(), step=60)
    assert len(list_checkpoints(best)) == 1
    runs.load_weights(best, {"net": other})
    assert _value_of(other) == 3.0


def test_files_at_the_top_of_a_folder_are_a_run_only_as_a_complete_generation(tmp_path):
    model, optimizer = _trained(0)
    generation = runs.save_checkpoint(
        tmp_path / "run", {"net": model}, _Cfg(), optimizers={"opt": optimizer}, state={"step": 3}
    )
    assert runs.latest_checkpoint(generation) == generation  # a generation folder given directly
    assert runs.load_training_state(generation)["step"] == 3
    # weights, state and an unstamped config.yaml at the top of a folder: no generation, no run
    flat = tmp_path / "flat"
    shutil.copytree(generation, flat)
    (flat / runs.CONFIG_FILE).write_text(yaml.safe_dump(to_dict(_Cfg()), sort_keys=False))
    assert not runs.is_run(flat)
    with pytest.raises(ConfigError, match=r"flat: not a complete checkpoint \(config.yaml belongs to another save"):
        runs.load_weights(flat, {"net": model})


# ---------------------------------------------------------------------------- incomplete generations


def test_newest_generation_with_a_foreign_file_is_skipped(tmp_path):
    _save(tmp_path / "other", 2)
    _save(tmp_path / "run", 1)
    newest = _save(tmp_path / "run", 2)
    # A training state of another save (same step, other save_id): a mixed pair must not be taken.
    shutil.copy(runs.latest_checkpoint(tmp_path / "other") / runs.STATE_FILE, newest / runs.STATE_FILE)
    assert runs.latest_checkpoint(tmp_path / "run").name == "step-000000001"
    _assert_current_step(tmp_path / "run", 1)


def test_newest_generation_with_a_torn_file_is_skipped(tmp_path):
    _save(tmp_path, 1)
    newest = _save(tmp_path, 2)
    weights = newest / runs.WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:-7])
    _assert_current_step(tmp_path, 1)
    # The next save does not count the torn one among the generations it keeps.
    _save(tmp_path, 3, keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step-000000003", "step-000000001"]


def test_state_that_cannot_be_read_back_is_refused_at_save_time(tmp_path):
    _save(tmp_path, 1)
    # A Path pickles fine but torch.load(weights_only=True) refuses it: found now, not at --resume.
    with pytest.raises(ValueError, match="cannot be read back"):
        runs.save_checkpoint(tmp_path, {"net": _model()}, _Cfg(), state={"step": 2, "data": Path("x")})
    _assert_current_step(tmp_path, 1)
    assert _leftovers(tmp_path) == []


def test_errors_name_the_folder_and_the_problem(tmp_path):
    with pytest.raises(ConfigError, match="run directory not found"):
        runs.load_weights(tmp_path / "nope", {"net": _model()})
    with pytest.raises(ConfigError, match="not a run directory"):
        runs.load_weights(tmp_path, {"net": _model()})
    assert not runs.is_run(tmp_path)
    (tmp_path / runs.CHECKPOINTS_DIR / ".tmp-5-abc").mkdir(parents=True)
    with pytest.raises(ConfigError, match=f"{tmp_path}: no complete checkpoint"):
        runs.latest_checkpoint(tmp_path)

    _save(tmp_path / "run", 1)
    with pytest.raises(ConfigError, match=r"net\.0\.weight has shape \(4, 3\) in the checkpoint but \(6, 3\)"):
        runs.load_weights(tmp_path / "run", {"net": _model(6)})
    with pytest.raises(ConfigError, match="no weights for module 'other'"):
        runs.load_weights(tmp_path / "run", {"other": _model()})
    with pytest.raises(ConfigError, match="no optimiser state for 'adam'"):
        runs.load_training_state(tmp_path / "run", {"adam": torch.optim.Adam(_model().parameters())})


# ---------------------------------------------------------------------------- kill -9 during saves

_WORKER = r"""
import os, sys, time
import torch
torch.set_num_threads(1)
from fdnet.runs import RunLock, save_checkpoint

WIDTH = 256  # two 256x256 layers: ~0.5 MB of weights, so a save takes measurable time


def save_forever(run_dir, first_step):
    torch.manual_seed(first_step)
    model = torch.nn.Sequential(torch.nn.Linear(WIDTH, WIDTH), torch.nn.Linear(WIDTH, WIDTH))
    optimizer = torch.optim.SGD(model.parameters(), lr=0.0)
    print(f"started {os.getpid()}", flush=True)
    for step in range(first_step, first_step + 100000):  # killed long before the end
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.fill_(step)
        optimizer.param_groups[0]["lr"] = float(step)
        save_checkpoint(run_dir, {"net": model}, {"width": WIDTH, "step": step}, {"opt": optimizer},
                        {"step": step, "marker": torch.full((3,), float(step))}, keep=2)


def hold_lock(run_dir):
    with RunLock(run_dir, command="lock-holder test"):
        print(f"locked {os.getpid()}", flush=True)
        time.sleep(120)  # killed long before the end


# A fork server: torch is imported once, each child forks from here in milliseconds. The first
# optimiser pulls in more of torch (about a second), so that happens here once too.
torch.optim.SGD(torch.nn.Linear(1, 1).parameters(), lr=0.0)
child = None
for line in sys.stdin:
    command, *args = line.split()
    if command == "reap":
        os.waitpid(child, 0)
        child = None
        print("reaped", flush=True)
        continue
    child = os.fork()
    if child == 0:
        try:
            if command == "save":
                save_forever(args[0], int(args[1]))
            elif command == "lock":
                hold_lock(args[0])
        finally:
            os._exit(0)
"""


@dataclass
class _KillCfg:
    width: int = 256
    step: int = 0


class _Worker:
    """The fork-server process above, with line replies read under a timeout (never hangs)."""

    def __init__(self, folder: Path):
        script = folder / "worker.py"
        script.write_text(_WORKER)
        env = dict(
            os.environ,
            OMP_NUM_THREADS="1",
            MKL_NUM_THREADS="1",
            PYTHONPATH=os.pathsep.join(filter(None, [str(SRC), os.environ.get("PYTHONPATH")])),
        )
        # stderr to a file: a pipe nobody reads could fill up and stall the worker.
        self.stderr_path = folder / "worker.err"
        with open(self.stderr_path, "w") as stderr:
            self.process = subprocess.Popen(
                [sys.executable, str(script)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=stderr,
                text=True,
                env=env,
            )
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.process.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def ask(self, command: str, timeout: float = 120.0) -> str:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            line = None
        if line is None:
            self.process.kill()
            pytest.fail(f"worker did not answer {command!r}: {self.stderr_path.read_text()[-2000:]}")
        return line

    def start(self, command: str) -> int:
        """Fork a child running ``command``; its pid once it is running."""
        reply = self.ask(command)
        return int(reply.split()[1])

    def kill(self, pid: int) -> None:
        """SIGKILL the child and wait until it is gone (reaped by the fork server)."""
        os.kill(pid, signal.SIGKILL)
        assert self.ask("reap") == "reaped"

    def close(self):
        self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    server = _Worker(tmp_path_factory.mktemp("worker"))
    yield server
    server.close()


def _assert_kill_step(run_dir, step):
    model = torch.nn.Sequential(torch.nn.Linear(256, 256), torch.nn.Linear(256, 256))
    optimizer = torch.optim.SGD(model.parameters(), lr=12345.0)
    metadata = runs.load_weights(run_dir, {"net": model})
    state = runs.load_training_state(run_dir, {"opt": optimizer})
    config = runs.load_config(run_dir, _KillCfg)
    assert int(metadata["step"]) == step
    assert _value_of(model) == step
    assert state["step"] == step and torch.equal(state["marker"], torch.full((3,), float(step)))
    assert optimizer.param_groups[0]["lr"] == step
    assert config.step == step


def test_sigkill_during_saves_always_leaves_a_complete_checkpoint(tmp_path, worker):
    run_dir = tmp_path / "run"
    kill_delays = random.Random(20240611)
    confirmed = 0  # the last step known to be published; it must never be lost
    interrupted = 0
    for round_ in range(12):
        pid = worker.start(f"save {run_dir} {confirmed + 1}")
        time.sleep(kill_delays.uniform(0.02, 0.4))
        worker.kill(pid)
        interrupted += bool(_leftovers(run_dir))

        current = runs.latest_checkpoint(run_dir)  # raises if no complete checkpoint is left
        step = int(
            runs.load_weights(
                current, {"net": torch.nn.Sequential(torch.nn.Linear(256, 256), torch.nn.Linear(256, 256))}
            )["step"]
        )
        assert step >= confirmed, f"round {round_}: step {confirmed} was published, now only {step}"
        _assert_kill_step(run_dir, step)

        # A new save (the resumed training's first) succeeds and clears the killed one's leftovers.
        model = _filled(torch.nn.Sequential(torch.nn.Linear(256, 256), torch.nn.Linear(256, 256)), step + 1)
        optimizer = torch.optim.SGD(model.parameters(), lr=float(step + 1))
        runs.save_checkpoint(
            run_dir,
            {"net": model},
            _KillCfg(step=step + 1),
            {"opt": optimizer},
            {"step": step + 1, "marker": torch.full((3,), float(step + 1))},
            keep=2,
        )
        confirmed = step + 1
        _assert_kill_step(run_dir, confirmed)
        assert _leftovers(run_dir) == []
        assert len(list_checkpoints(run_dir)) <= 2
    # Not asserted (timing): how many kills hit a save part way; shown with -s for the curious.
    print(f"{interrupted} of 12 kills left a partial save behind")


# ---------------------------------------------------------------------------- full disk


class _FullDisk:
    """A file object that writes part of what it is given, then fails as a full disk does."""

    def __init__(self, handle):
        self.handle = handle

    def write(self, data):
        self.handle.write(bytes(data)[: max(1, len(data) // 3)])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self.handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.handle.close()


@pytest.mark.parametrize("failing_file", [runs.WEIGHTS_FILE, runs.STATE_FILE, runs.CONFIG_FILE])
def test_full_disk_part_way_keeps_the_previous_checkpoint(tmp_path, monkeypatch, failing_file):
    _save(tmp_path, 1)
    real_open = builtins.open

    def open_on_a_full_disk(file, mode="r", *args, **kwargs):
        handle = real_open(file, mode, *args, **kwargs)
        writing = any(c in mode for c in "wax")
        if (
            writing
            and isinstance(file, (str, os.PathLike))
            and Path(file).name == failing_file
            and Path(tmp_path) in Path(file).parents
        ):
            return _FullDisk(handle)
        return handle

    with monkeypatch.context() as patch:
        patch.setattr(builtins, "open", open_on_a_full_disk)
        with pytest.raises(ConfigError, match="no space left") as failure:
            _save(tmp_path, 2)
    assert "step-000000001 is still the current checkpoint" in str(failure.value)
    # an operating-system error, not a setting: the CLI names it as such, callers can read errno
    assert isinstance(failure.value, OutputError) and failure.value.errno == errno.ENOSPC
    _assert_current_step(tmp_path, 1)
    assert _leftovers(tmp_path) == []

    _save(tmp_path, 2)  # space is back
    _assert_current_step(tmp_path, 2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step-000000002", "step-000000001"]


@pytest.fixture
def tiny_filesystem(tmp_path):
    """A real 2 MiB filesystem (tmpfs) to fill up; skipped where mounting is not permitted."""
    mount_point = tmp_path / "tiny"
    mount_point.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command here; the simulated full-disk test covers this case")
    result = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount_point)], capture_output=True, text=True
    )
    if result.returncode != 0:
        pytest.skip(
            "mounting a 2 MiB tmpfs is not permitted here (needs root outside a restricted "
            f"container: {result.stderr.strip() or result.returncode}); "
            "the simulated full-disk test covers this case"
        )
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", str(mount_point)], capture_output=True)


def test_full_disk_on_a_real_filesystem(tiny_filesystem):
    run_dir = tiny_filesystem / "run"

    def model(value=0.0):
        return _filled(torch.nn.Sequential(torch.nn.Linear(300, 300)), value)  # ~0.36 MB of weights

    runs.save_checkpoint(run_dir, {"net": model(1)}, _Cfg(step=1), state={"step": 1})

    filler = tiny_filesystem / "filler"
    with open(filler, "wb", buffering=0) as handle:
        try:
            for _ in range(64):  # 64 x 64 KiB > 2 MiB: bounded, always ends with the disk full
                handle.write(b"\0" * 65536)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    os.truncate(filler, max(0, filler.stat().st_size - 100_000))  # room for part of a save only

    with pytest.raises(ConfigError, match="no space left"):
        runs.save_checkpoint(run_dir, {"net": model(2)}, _Cfg(step=2), state={"step": 2})
    check = model()
    assert runs.load_weights(run_dir, {"net": check})["step"] == "1" and _value_of(check) == 1
    assert runs.load_training_state(run_dir)["step"] == 1
    assert runs.load_config(run_dir, _Cfg).step == 1
    assert _leftovers(run_dir) == []

    filler.unlink()
    runs.save_checkpoint(run_dir, {"net": model(2)}, _Cfg(step=2), state={"step": 2})
    assert runs.load_weights(run_dir, {"net": check})["step"] == "2" and _value_of(check) == 2


# ---------------------------------------------------------------------------- run lock


def test_run_lock_refuses_a_second_holder_until_the_first_is_killed(tmp_path, worker):
    run_dir = tmp_path / "run"
    pid = worker.start(f"lock {run_dir}")
    try:
        with pytest.raises(ConfigError) as refused:
            with runs.RunLock(run_dir, command="fdnet train"):
                pass
        message = str(refused.value)
        assert f"{run_dir} is in use by process {pid} (lock-holder test, started " in message
        assert message.endswith("wait for it to finish or stop it")
    finally:
        worker.kill(pid)
    assert (run_dir / runs.LOCK_FILE).exists()  # stale file left by kill -9 ...
    with runs.RunLock(run_dir) as lock:  # ... does not block
        assert lock.held
        assert yaml.safe_load((run_dir / runs.LOCK_FILE).read_text())["pid"] == os.getpid()


def test_run_lock_in_one_process_refuses_a_second_and_frees_on_exit(tmp_path):
    with runs.RunLock(tmp_path, command="first"):
        with pytest.raises(ConfigError, match=f"in use by process {os.getpid()} \\(first, started"):
            runs.RunLock(tmp_path, command="second").acquire()
    with runs.RunLock(tmp_path, command="third"):
        pass


# ---------------------------------------------------------------------------- settings


def test_record_and_read_changes(tmp_path):
    assert runs.read_changes(tmp_path) == []
    runs.record_changes(tmp_path, 1200, ["train.lr: saved 0.001, requested 0.0005"], "fdnet train --resume --override")
    runs.record_changes(tmp_path, 1500, [], "no change: nothing recorded")
    runs.record_changes(tmp_path, 3000, ["train.steps: saved 3000, requested 6000", "a.b: saved 1, requested 2"])
    changes = runs.read_changes(tmp_path)
    assert [(c["step"], c["changes"]) for c in changes] == [
        (1200, ["train.lr: saved 0.001, requested 0.0005"]),
        (3000, ["train.steps: saved 3000, requested 6000", "a.b: saved 1, requested 2"]),
    ]
    assert changes[0]["command"] == "fdnet train --resume --override" and changes[0]["time"]
    (tmp_path / runs.CHANGES_FILE).write_text("step: 3\n")
    with pytest.raises(ConfigError, match="changes.yaml: expected a list"):
        runs.read_changes(tmp_path)


def test_config_differences():
    saved, requested = _Cfg(), _Cfg(net=_Net(width=8), lr=0.1)
    assert runs.config_differences(saved, requested) == [
        "lr: saved 0.001, requested 0.1",
        "net.width: saved 4, requested 8",
    ]
    assert runs.config_differences(saved, requested, keys=["net.width"]) == ["net.width: saved 4, requested 8"]
    assert runs.config_differences(saved, {"net": {"width": 4}, "lr": 0.001, "step": 0}) == []


def test_a_damaged_newest_checkpoint_is_skipped_with_a_warning_naming_it(tmp_path, caplog):
    _save(tmp_path, 1)
    _save(tmp_path, 2)
    newest = runs.latest_checkpoint(tmp_path)
    (newest / runs.WEIGHTS_FILE).write_bytes(b"damaged")
    with caplog.at_level("WARNING"):
        used = runs.latest_checkpoint(tmp_path)
    assert used != newest and used.name.startswith("step-000000001")
    assert f"skipped the newest checkpoint(s), damaged ({newest.name}" in caplog.text and used.name in caplog.text


@pytest.mark.parametrize("fill", [0x3F, 0xFF])
def test_bytes_rotted_inside_the_weights_or_the_state_are_refused_naming_the_file(tmp_path, fill):
    """Bytes overwritten inside the tensor data leave a file safetensors reads without a word (other
    numbers, or NaN for 0xff): the checksum saved with the generation refuses it."""
    _save(tmp_path, 1)
    folder = runs.latest_checkpoint(tmp_path)
    weights = folder / runs.WEIGHTS_FILE
    data = bytearray(weights.read_bytes())
    data[-16:-8] = bytes([fill]) * 8  # inside the last tensor's data, past the header
    weights.write_bytes(bytes(data))
    with pytest.raises(ConfigError, match=r"model\.safetensors: the weights do not match the checksum"):
        runs.load_weights(tmp_path, {"net": _model()})
    _save(tmp_path / "b", 1)
    state = runs.latest_checkpoint(tmp_path / "b") / checkpoints.STATE_FILE
    data = bytearray(state.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 4] = bytes([fill]) * 4
    state.write_bytes(bytes(data))
    with pytest.raises(ConfigError, match=r"training_state\.pt: the training state does not match the checksum"):
        runs.load_training_state(tmp_path / "b", {"opt": torch.optim.SGD(_model().parameters(), lr=1.0)})
