"""Data-parallel training under torchrun (fdnet.training.distributed): 2 gloo processes on the CPU.

Each launch runs ``torchrun --standalone --nproc-per-node 2`` on a small wrapper around
``fdnet.cli.main`` that, after the training, saves the weights its rank holds (test-only code,
kept out of the library), so the test can compare what the two ranks ended with.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch

from fdnet import runs
from fdnet.cli import main
from fdnet.methods.fdnet.config import FDNetRunConfig
from fdnet.methods.fdnet.model import FDNet
from tests.training.test_loop import make_dataset

# Saves the weights this rank holds when Trainer.fit returns (or raises), as rank-<RANK>.pt.
WRAPPER = """
import os, sys
import torch
from fdnet.training import loop

fit = loop.Trainer.fit

def fit_then_dump(self, *args, **kwargs):
    try:
        return fit(self, *args, **kwargs)
    finally:
        weights = {f"{name}.{key}": value.detach().cpu().clone()
                   for name, module in self.method.modules().items()
                   for key, value in module.state_dict().items()}
        torch.save(weights, os.path.join(os.environ["DUMP_DIR"], f"rank-{os.environ['RANK']}.pt"))

loop.Trainer.fit = fit_then_dump
from fdnet.cli import run
run(sys.argv[1:])
"""


def _torchrun(tmp_path, *args, dump=None, nproc=2):
    """Run ``fdnet ARGS`` under torchrun with ``nproc`` CPU processes (through the dumping wrapper
    when ``dump`` is a folder, else as ``-m fdnet``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    env.update(OMP_NUM_THREADS="1", CUDA_VISIBLE_DEVICES="")
    target = ["-m", "fdnet"]
    if dump is not None:
        dump.mkdir(parents=True, exist_ok=True)
        wrapper = tmp_path / "dump_wrapper.py"
        wrapper.write_text(WRAPPER)
        env["DUMP_DIR"] = str(dump)
        target = [str(wrapper)]
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc-per-node={nproc}",
        *target,
        *map(str, args),
    ]
    # the timeout only guards against a hang (a rank left waiting in a collective)
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=300)


def _dumped(folder):
    return [torch.load(folder / f"rank-{r}.pt", weights_only=True) for r in (0, 1)]


def _saved_fdnet_weights(run_dir):
    model = FDNet(runs.load_config(run_dir, FDNetRunConfig).model)
    runs.load_weights(run_dir, model.named_parts())
    return {
        f"{name}.{key}": value
        for name, module in model.named_parts().items()
        for key, value in module.state_dict().items()
    }


def _assert_same(a, b, what):
    assert a.keys() == b.keys(), what
    different = [k for k in a if not torch.equal(a[k], b[k])]
    assert not different, f"{what}: {different[:5]} differ"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("distributed") / "data")


@pytest.fixture(scope="module")
def stopped_run(tmp_path_factory, data):
    """A 2-process tiny run stopped by the time budget after its first step (a stop both ranks
    agree on); tests work on copies."""
    folder = tmp_path_factory.mktemp("stopped")
    stopped = _torchrun(folder, *TINY(data), "--out", folder / "run", "--max-minutes", "0")
    assert stopped.returncode == 0, stopped.stderr
    assert "time limit at step 1/8" in stopped.stdout
    return folder / "run"


def TINY(data):
    return ["train", "--data", data, "--preset", "tiny", "--no-progress"]


def test_two_processes_train_identical_weights_record_world_size_and_resume_exactly(tmp_path, data, stopped_run):
    common = TINY(data)

    # an uninterrupted 2-process run: 8 steps, both ranks hold the same weights at the end
    whole = _torchrun(tmp_path, *common, "--out", tmp_path / "whole", dump=tmp_path / "whole-ranks")
    assert whole.returncode == 0, whole.stderr
    assert "finished at step 8/8" in whole.stdout and "on 2 processes" in whole.stdout
    assert whole.stdout.count("finished at step") == 1, "only rank 0 reports"
    assert whole.stderr.count("fdnet train: preset tiny, conditions") == 1, "only rank 0 logs"
    rank0, rank1 = _dumped(tmp_path / "whole-ranks")
    _assert_same(rank0, rank1, "rank 0 and rank 1 after training")
    _assert_same(_saved_fdnet_weights(tmp_path / "whole"), rank0, "saved checkpoint and rank 0")

    state = runs.load_training_state(tmp_path / "whole")
    assert state["world_size"] == 2 and len(state["rank_states"]) == 2
    generators = [r["method_state"]["sampler_generator"] for r in state["rank_states"]]
    assert not torch.equal(*generators), "the ranks must draw different batches"
    assert torch.equal(state["method_state"]["sampler_generator"], generators[0])

    # the same run stopped by the time budget after its first step ...
    part = tmp_path / "part"
    shutil.copytree(stopped_run, part)
    assert runs.load_training_state(part)["step"] == 1

    # ... refuses a resume by one process (the message: the next test) ...
    single = tmp_path / "single"
    shutil.copytree(part, single)
    assert main(["train", "--data", str(data), "--out", str(single), "--resume", "--no-progress"]) == 2
    assert runs.load_training_state(single)["step"] == 1
    # ... continues with one process when told to, recording the change ...
    assert main(["train", "--data", str(data), "--out", str(single), "--resume", "--override", "--no-progress"]) == 0
    assert runs.load_training_state(single)["world_size"] == 1
    assert runs.read_changes(single)[0]["changes"] == ["world_size: saved 2, requested 1"]

    # ... and resumed by 2 processes ends exactly where the uninterrupted run did, on both ranks
    resumed = _torchrun(tmp_path, *common, "--out", part, "--resume", dump=tmp_path / "part-ranks")
    assert resumed.returncode == 0, resumed.stderr
    assert "finished at step 8/8" in resumed.stdout
    for rank, weights in enumerate(_dumped(tmp_path / "part-ranks")):
        _assert_same(weights, rank0, f"resumed rank {rank} and the uninterrupted run")
    assert not runs.read_changes(part)


def test_resume_with_another_world_size_is_refused_naming_both(tmp_path, data, stopped_run, capsys):
    part = tmp_path / "part"
    shutil.copytree(stopped_run, part)
    assert main(["train", "--data", str(data), "--out", str(part), "--resume", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "fdnet train: error:" in err and "world size 2" in err and "world size 1" in err and "--override" in err

    # a failure on rank 0 alone (a fresh run into a folder that holds one) stops both ranks with its message
    again = _torchrun(tmp_path, *TINY(data), "--out", part)
    assert again.returncode != 0
    assert "already holds a run" in again.stderr
    assert "stopped because process 0 of 2 failed" in again.stderr
    assert runs.load_training_state(part)["step"] == 1


def test_calc_trains_on_two_processes(tmp_path, data):
    result = _torchrun(
        tmp_path,
        "train",
        "calc",
        "--data",
        data,
        "--preset",
        "tiny",
        "--steps",
        "4",
        "--threads",
        "1",
        "--no-progress",
        "--out",
        tmp_path / "calc",
        dump=tmp_path / "ranks",
    )
    assert result.returncode == 0, result.stderr
    assert "finished at step 4/4" in result.stdout and "on 2 processes" in result.stdout
    rank0, rank1 = _dumped(tmp_path / "ranks")
    _assert_same(rank0, rank1, "CALC rank 0 and rank 1 after training")
    state = runs.load_training_state(tmp_path / "calc")
    assert state["world_size"] == 2
    assert state["rank_states"][0]["method_state"]["numpy_rng"] != state["rank_states"][1]["method_state"]["numpy_rng"]


# ---------------------------------------------------------------------- single process, no launcher


def test_context_from_the_environment():
    from fdnet.errors import ConfigError
    from fdnet.training.distributed import DistributedContext

    single = DistributedContext.from_env({})
    assert (single.world_size, single.rank, single.is_main, single.launched) == (1, 0, True, False)
    ranked = DistributedContext.from_env({"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1"})
    assert (ranked.world_size, ranked.rank, ranked.local_rank, ranked.is_main) == (4, 3, 1, False)
    assert ranked.rank_seed(10) == 13 and single.rank_seed(10) == 10
    with pytest.raises(ConfigError, match="RANK is not"):
        DistributedContext.from_env({"WORLD_SIZE": "2"})
    with pytest.raises(ConfigError, match="0 <= RANK < WORLD_SIZE"):
        DistributedContext.from_env({"WORLD_SIZE": "2", "RANK": "2"})
    with pytest.raises(ConfigError, match="not an integer"):
        DistributedContext.from_env({"WORLD_SIZE": "two", "RANK": "0"})


def test_a_single_process_context_changes_nothing():
    from fdnet.training.distributed import DistributedContext, merge_rank_state

    context = DistributedContext()
    layer = torch.nn.Linear(3, 2)
    optimizer = torch.optim.SGD(layer.parameters(), lr=0.1)
    layer(torch.ones(1, 3)).sum().backward()
    before = [p.grad.clone() for p in layer.parameters()]
    assert context.average_gradients(optimizer, torch.tensor(1.5)) is True
    assert context.average_gradients(optimizer, torch.tensor(float("nan"))) is False
    assert all(torch.equal(a, p.grad) for a, p in zip(before, layer.parameters()))
    assert context.agree(True, False) == (True, False)
    assert context.gather_to_main("x") == ["x"] and context.broadcast(7) == 7
    assert context.collectively(lambda: 5, main_only=True) == 5
    # a resumed rank: the shared state with its own entries
    shared = {"generator": 0, "cache": "rank 0's"}
    assert merge_rank_state(shared, {"generator": 1, "cache": "mine"}, ("generator",)) == {
        "generator": 1,
        "cache": "rank 0's",
    }
    assert merge_rank_state(shared, {"generator": 1}, None) == {"generator": 1}


def test_a_non_finite_loss_stops_before_the_optimiser_step(tmp_path, data, monkeypatch):
    from fdnet.config import replace_dotted
    from fdnet.methods.fdnet import losses
    from fdnet.methods.fdnet.config import preset
    from fdnet.methods.fdnet.training import FDNetTraining, load_training_images

    config = replace_dotted(preset("tiny"), {"data.root": str(data)})
    method = FDNetTraining(config, load_training_images(config))
    before = {k: v.clone() for k, v in method.model.state_dict().items()}
    monkeypatch.setattr(losses, "reconstruction_loss", lambda target, output, reduction: output.sum() * float("nan"))
    with pytest.raises(FloatingPointError, match="loss became nan at step 0"):
        method.train_step(0)
    assert all(
        torch.equal(before[k], v)
        for k, v in method.model.state_dict().items()
        if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))
    )


def test_exit_process_after_a_process_group_runs_exit_handlers_flushes_and_keeps_the_code(tmp_path):
    marker = tmp_path / "atexit-ran"
    script = f"""
import atexit, pathlib, sys
from fdnet import torchrun
atexit.register(lambda: pathlib.Path({str(marker)!r}).write_text("yes"))
torchrun._joined_a_group = True
sys.stdout.write("unflushed output")
torchrun.exit_process(3)
print("not reached")
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 3 and result.stdout == "unflushed output", (result.stdout, result.stderr)
    assert marker.read_text() == "yes"
    # a process that never joined a group exits the ordinary way
    plain = subprocess.run(
        [sys.executable, "-c", "from fdnet import torchrun; torchrun.exit_process(4)"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert plain.returncode == 4
