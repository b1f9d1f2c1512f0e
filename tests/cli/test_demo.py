"""The README's main job, shrunk: synth -> train (tiny preset) -> evaluate, all in one command."""

import json

from fdnet.cli import main


def test_demo_runs_end_to_end_with_tiny_preset(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--preset", "tiny", "--num-frames", "40", "--method", "fdnet,sad"]) == 0
    for pair in ("night-summer", "winter-summer"):
        results = json.loads((out / f"results-{pair}.json").read_text())["results"]
        assert [r["method"] for r in results] == ["fdnet", "sad"]
        assert all(0.0 <= r["recall_at_n"]["1"] <= 1.0 for r in results)
        assert (out / f"plots-{pair}" / "pr_curves.png").stat().st_size > 0
    from fdnet import runs

    assert runs.is_run(out / "fdnet-run")
    assert "SYNTHETIC" in (out / "route" / "README.txt").read_text()
    printed = capsys.readouterr().out
    assert "R@1" in printed and "demo finished" in printed


def test_demo_rejects_too_short_route(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--num-frames", "10"]) == 2
    assert "at least 40" in capsys.readouterr().err
