"""Every JSON fdnet writes records where its numbers came from (fdnet.provenance): fdnet's version
and git commit, the libraries' versions, the device and CPU, the seeds and the command."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np

from fdnet.cli import main
from fdnet.provenance import provenance

REPO = Path(__file__).resolve().parents[1]
KEYS = {
    "fdnet_version",
    "git",
    "python",
    "libraries",
    "device",
    "cpu",
    "cpu_count",
    "platform",
    "seeds",
    "command",
    "created",
}


def _in_checkout() -> bool:
    try:
        found = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True)
    except OSError:
        return False
    return found.returncode == 0


def _is_in_history(commit: str) -> bool:
    """Whether ``commit`` is HEAD or before it (commits made while the tests run move HEAD on)."""
    found = subprocess.run(
        ["git", "-C", str(REPO), "merge-base", "--is-ancestor", commit, "HEAD"], capture_output=True, text=True
    )
    return found.returncode == 0


def _check(record: dict, command: str | None = None) -> None:
    from fdnet.version import __version__

    assert KEYS <= set(record)
    assert record["fdnet_version"] == __version__
    assert set(record["libraries"]) == {"torch", "numpy", "faiss"} and record["libraries"]["numpy"] == np.__version__
    assert record["cpu"] and record["device"]
    if _in_checkout() and (REPO / "src" / "fdnet").resolve() == Path(__import__("fdnet").__file__).parent.resolve():
        assert len(record["git"]["commit"]) == 40 and _is_in_history(record["git"]["commit"])
        assert isinstance(record["git"]["dirty"], bool)
    if command is not None:
        assert record["command"] == command


def test_the_record_names_versions_machine_seeds_and_command():
    record = provenance("fdnet evaluate --x", seeds={"runtime": 3}, device="cpu")
    _check(record, "fdnet evaluate --x")
    assert record["seeds"] == {"runtime": 3} and record["device"] == "cpu"
    json.dumps(record)  # plain JSON


def test_evaluate_json_records_it(tmp_path):
    s = np.eye(3) + 0.1
    np.save(tmp_path / "s.npy", s)
    (tmp_path / "gt.csv").write_text("query_index,reference_indices\n0,0\n1,1\n2,2\n")
    argv = [
        "evaluate",
        "--similarity",
        str(tmp_path / "s.npy"),
        "--ground-truth",
        str(tmp_path / "gt.csv"),
        "--json",
        str(tmp_path / "e.json"),
    ]
    assert main(argv) == 0
    _check(json.loads((tmp_path / "e.json").read_text())["provenance"], "fdnet " + " ".join(argv))


def test_loop_closure_report_records_it(tmp_path):
    from PIL import Image

    rng = np.random.default_rng(0)
    (tmp_path / "traverse").mkdir()
    for i in range(6):
        Image.fromarray(rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)).save(tmp_path / "traverse" / f"{i}.png")
    argv = [
        "loop-closure",
        "--images",
        str(tmp_path / "traverse"),
        "--method",
        "raw",
        "--sequence-length",
        "1",
        "--threshold",
        "0.5",
        "--accept",
        "margin",
        "--out",
        str(tmp_path / "e.csv"),
        "--report",
        str(tmp_path / "r.json"),
        "--workers",
        "0",
    ]
    assert main(argv) == 0
    _check(json.loads((tmp_path / "r.json").read_text())["provenance"], "fdnet " + " ".join(argv))


def test_benchmark_json_records_it(tmp_path):
    argv = [
        "benchmark",
        "--parts",
        "scale",
        "--threads",
        "1",
        "--map-size",
        "50",
        "--scale-dim",
        "8",
        "--indexes",
        "flat",
        "--queries",
        "5",
        "--json",
        str(tmp_path / "b.json"),
    ]
    assert main(argv) == 0
    record = json.loads((tmp_path / "b.json").read_text())["provenance"]
    _check(record)
    assert record["seeds"]["random_map"] == 0
