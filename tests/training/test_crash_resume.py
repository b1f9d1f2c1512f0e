"""kill -9 at random moments of a training that checkpoints every step, then --resume: the run
always resumes, and the end result is the uninterrupted run's, weight for weight."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import torch

from fdnet import runs
from fdnet.methods.fdnet.config import FDNetRunConfig
from fdnet.methods.fdnet.model import FDNet
from tests.training.test_loop import make_dataset

STEPS = ["--set", "schedule.joint_steps=150", "--set", "runtime.checkpoint_every=1", "--set", "runtime.threads=1"]


def _train(data, out, *extra):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fdnet",
            "train",
            "--data",
            str(data),
            "--preset",
            "tiny",
            "--out",
            str(out),
            "--no-progress",
            *STEPS,
            *extra,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )


def _weights(run_dir):
    config = runs.load_config(run_dir, FDNetRunConfig)
    model = FDNet(config.model)
    runs.load_weights(run_dir, model.named_parts())
    return model.state_dict()


def test_sigkill_during_checkpoint_saves_then_resume_matches_the_uninterrupted_run(tmp_path):
    data = make_dataset(tmp_path / "data")
    whole = _train(data, tmp_path / "whole")
    assert whole.wait(timeout=300) == 0, whole.stderr.read().decode()

    rng = np.random.default_rng(7)
    out = tmp_path / "killed"
    kills = 0
    for attempt in range(5):
        process = _train(data, out, *(["--resume"] if runs.is_run(out) else []))
        deadline = time.monotonic() + 120
        while not runs.is_run(out) and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(float(rng.uniform(0.0, 0.8)))
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
            kills += 1
        process.wait(timeout=60)
        # whatever instant the kill hit, a complete checkpoint is there and agrees with itself
        state = runs.load_training_state(out)
        assert state["step"] >= 1
    assert kills >= 3, "the training finished before it could be killed; make the schedule longer"
    final = _train(data, out, "--resume")
    assert final.wait(timeout=300) == 0, final.stderr.read().decode()
    assert runs.load_training_state(out)["step"] == runs.load_training_state(tmp_path / "whole")["step"]
    expected, got = _weights(tmp_path / "whole"), _weights(out)
    for name, value in expected.items():
        assert torch.equal(value, got[name]), name
    steps = [int(line.split(",")[0]) for line in (out / "log.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 155
