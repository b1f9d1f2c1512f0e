"""On real data, FDNet's content vector beats the frozen trunk it reads, after a short training
on other frames (no test frame seen; no place labels used)."""

from __future__ import annotations

import pytest

from fdnet.cli import main

from conftest import require_shared


@pytest.mark.shared_data
@pytest.mark.slow
def test_fdnet_beats_the_trunk_alone_on_held_out_nordland_frames(tmp_path, capsys):
    import json

    root = require_shared("nordland_trimmed")
    run = tmp_path / "run"
    assert main(["train", "--data", str(root), "--preset", "cpu", "--out", str(run), "--conditions", "summer,winter",
                 "--frames", "0:400", "--no-progress",
                 "--set", "schedule.pretrain_autoencoder_steps=5", "--set", "schedule.pretrain_critic_steps=5",
                 "--set", "schedule.joint_steps=20", "--set", "runtime.checkpoint_every=1000"]) == 0
    out = tmp_path / "results.json"
    assert main(["evaluate", "--data", str(root), "--reference", "summer", "--query", "winter",
                 "--frames", "1576:1876", "--tolerance", "0", "--method", "fdnet,trunk", "--checkpoint", str(run),
                 "--json", str(out), "--threads", "2"]) == 0
    results = {r["method"]: r for r in json.loads(out.read_text())["results"]}
    fdnet, trunk = results["fdnet"]["recall_at_n"]["1"], results["trunk"]["recall_at_n"]["1"]
    assert fdnet > trunk, (fdnet, trunk)
