"""On real data, FDNet's 512-long content vector beats the frozen trunk it reads and that trunk
PCA-whitened to the same length on the same training frames, after a short training on other
frames (no test frame seen; no place labels used)."""

from __future__ import annotations

import pytest

from fdnet.cli import main

from conftest import require_shared


@pytest.mark.shared_data
@pytest.mark.slow
def test_fdnet_beats_the_trunk_and_its_whitening_on_held_out_nordland_frames(tmp_path, capsys):
    import json

    root = require_shared("nordland_trimmed")
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--data",
                str(root),
                "--preset",
                "cpu",
                "--out",
                str(run),
                "--conditions",
                "summer,winter",
                "--frames",
                "0:800",
                "--no-progress",
                "--set",
                "schedule.pretrain_autoencoder_steps=5",
                "--set",
                "schedule.pretrain_critic_steps=5",
                "--set",
                "schedule.joint_steps=20",
                "--set",
                "runtime.checkpoint_every=1000",
            ]
        )
        == 0
    )
    out = tmp_path / "results.json"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(root),
                "--reference",
                "summer",
                "--query",
                "winter",
                "--frames",
                "1576:1876",
                "--tolerance",
                "0",
                "--method",
                "fdnet,trunk,trunk-whitened",
                "--checkpoint",
                str(run),
                "--fit",
                str(root),
                "--fit-frames",
                "0:800",
                "--json",
                str(out),
                "--threads",
                "2",
            ]
        )
        == 0
    )
    results = {r["method"]: r for r in json.loads(out.read_text())["results"]}
    assert results["fdnet"]["settings"]["vector_length"] == 512
    assert results["trunk-whitened"]["settings"]["dim"] == 512
    fdnet, trunk, whitened = (results[m]["recall_at_n"]["1"] for m in ("fdnet", "trunk", "trunk-whitened"))
    assert fdnet > max(trunk, whitened), (fdnet, trunk, whitened)
